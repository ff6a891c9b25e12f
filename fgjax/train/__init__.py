"""fgjax.train."""
