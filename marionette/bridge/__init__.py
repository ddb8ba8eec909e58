"""The bridge: state → world skeletons → camera → a lossless 10-bit G-buffer video (zero parameters)."""

from .gbuffer import GBufferFrame, GBufferMeta, decode_gbuffer, write_gbuffer

__all__ = ["GBufferFrame", "GBufferMeta", "decode_gbuffer", "write_gbuffer"]
