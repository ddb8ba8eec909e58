"""The observation model: pose-control video + first frame → RGB video (a small video DiT trained by rectified flow)."""
