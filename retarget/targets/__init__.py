"""The artist's target key shapes: loaded, blended with weights (004 section 5)."""
