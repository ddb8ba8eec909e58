"""The bridge: state → world skeletons → camera → a lossless 10-bit G-buffer video (zero parameters)."""
