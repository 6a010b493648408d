"""The grounding heads (box regression, cells), their shared query layers and their loss."""
