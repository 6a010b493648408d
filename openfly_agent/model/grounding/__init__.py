"""The grounding heads (box regression, cells), their loss and the box token."""
