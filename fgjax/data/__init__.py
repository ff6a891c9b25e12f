"""fgjax.data."""
