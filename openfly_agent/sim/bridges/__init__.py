"""Bridges to real engines (UnrealCV, AirSim, 3DGS SIBR HTTP), speaking their wire protocols."""
