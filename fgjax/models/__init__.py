"""fgjax.models."""
