"""Companion-computer velocity hold from optical flow, gyro and range (Belfadel et al., eq. 15 + PI)."""
