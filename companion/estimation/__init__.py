"""Estimation: the leader tracker (constant-velocity Kalman filter on the relative position)."""
