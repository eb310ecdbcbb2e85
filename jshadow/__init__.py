"""jshadow."""
