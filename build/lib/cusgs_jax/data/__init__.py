"""Scene data: COLMAP reconstructions, images and the built-in demo scene."""
