"""Importers of third-party logs into the columnar ``Recording``."""
