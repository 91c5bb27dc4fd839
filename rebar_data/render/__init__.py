"""Open3D offscreen rendering: RGB, exact depth and instance ids, sensor effects."""
