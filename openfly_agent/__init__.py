"""openfly-agent: OpenFly-Agent, keyframe-aware aerial vision-language navigation, in PyTorch."""

__version__ = "0.1.0"
