"""What a filter knows of the lane state and how far to trust it: state sources,
intervals, monitors, and the fallback from odometry and the map."""
