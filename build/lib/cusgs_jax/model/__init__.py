"""The model: anchors (every per-anchor array), their decoding into Gaussians, feature queries and read-out."""
