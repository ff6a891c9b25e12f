"""fgjax.render."""
