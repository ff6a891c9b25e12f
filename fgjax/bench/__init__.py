"""fgjax.bench."""
