"""The vision backbones (fused DINOv2 + SigLIP ViTs, the tiny CNN) and the vision config (the image transform is
the processor's, model/processor.py; the projector the network's, model/network.py)."""
