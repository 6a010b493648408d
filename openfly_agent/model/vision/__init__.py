"""The vision backbones (fused DINOv2 + SigLIP ViTs, the tiny CNN), the image transform and the projector."""
