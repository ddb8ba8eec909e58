"""A small procedural game that writes recordings in the public WildWorld layout.

It is the embedded default data of the project: a drake and a hunter with a greatsword fight on a
stage near (x, z) = (−950, 850) with a hill, a valley spanned by a bridge and a wall. See
docs/formats.md, "Synthetic recordings".
"""

from . import terrain
from .game import generate, load_truth, world_skeletons_at
from .terrain import StageTerrain

__all__ = ["StageTerrain", "generate", "load_truth", "terrain", "world_skeletons_at"]
