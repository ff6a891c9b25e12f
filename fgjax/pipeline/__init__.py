"""fgjax.pipeline."""
