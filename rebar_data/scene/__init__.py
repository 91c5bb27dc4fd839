"""Scene randomizers: lighting, materials, surroundings, cameras and sensor effects."""
