"""Drift and creep models and the Kalman filter that tracks them."""
