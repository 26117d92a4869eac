"""Barriers that keep the car clear of other cars."""
