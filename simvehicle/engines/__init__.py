"""Engines that fly the models: the fast numba simulator, the scenarios, flight generation."""
