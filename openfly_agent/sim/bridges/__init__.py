"""Bridges to real engines over their wire protocols: `unrealcv`, `airsim` (msgpack-RPC), `gs_http` (SIBR).

Import the engine module you need; `airsim` loads `msgpack` only when it connects. See docs/BRIDGES.md.
"""
