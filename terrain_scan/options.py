"""A scan's options (``ScanOptions``: the depth decoder and every knob of ``terrain_scan.knobs``) and where a corpus
keeps its last scan's (``meta/scan.json``). Importable without open3d: ``marionette inspect`` shows them."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from marionette.corpus import paths
from marionette.io import read_json, text_sha256, write_json
from terrain_scan.depth import DepthDecoder
from terrain_scan.knobs import CHECK_KNOBS, DERIVE_KNOBS, KNOBS, knob_ok
from terrain_scan.layers import ALIAS_DOMINANCE, ALIAS_FRACTION, ALIAS_SUPPORT

# A fitting depth mapping puts a recording's scanned ground within centimetres of its characters' feet (at most 6 cm
# over twelve recordings of three hidden mappings); a wrong one, 0.9 m or more, or no ground where the feet stood:
# docs/tradeoffs.md, "A wrong depth mapping".
MAX_CONTACT_GAP_M = 0.5

# 2: image-space steepness test, 20 m depth range; 3: edge leaks dropped; 4: observations keep the edges they hug;
# 5: a recording's voxel means in float64 world coordinates (``accumulate.VoxelMeans``)
SCAN_VERSION = "5"


@dataclass(frozen=True)
class ScanOptions:
    """How depth becomes observations and observations a stage: the depth decoder and every knob of ``KNOBS``
    (defaults: the values tuned on the synthetic game, ``docs/tradeoffs.md``). A corpus keeps the options its
    last scan used (``meta/scan.json``: ``stored``), so a later scan, ingest's and the flows' included, scans
    with them unless told otherwise."""

    decoder: dict = field(default_factory=lambda: DepthDecoder.synthetic().to_json())
    frame_stride: int = 1
    depth_subsample: int = 1
    voxel_m: float = 0.25
    max_depth_m: float = 20.0
    min_normal_y: float = 0.5
    image_normal_y: float = 0.8
    edge_rel: float = 0.1
    edge_m: float = 0.1
    smooth_radius: int = 3
    smooth_tol: float = 1.0
    normal_radius_voxels: float = 2.0
    mask_radius_scale: float = 3.0
    mask_margin_m: float = 0.3
    contact_speed: float = 0.2
    contact_window: int = 2
    contact_tol_m: float = 0.05
    contact_hits: int = 1
    alias_fraction: float = ALIAS_FRACTION
    alias_dominance: float = ALIAS_DOMINANCE
    alias_support: int = ALIAS_SUPPORT
    max_contact_gap_m: float = MAX_CONTACT_GAP_M

    def __post_init__(self) -> None:
        for name, (check, _) in KNOBS.items():
            v = getattr(self, name)
            if not knob_ok(check, v):
                raise ValueError(f"scan option {name} must be {check}, not {v!r}")
            if check.startswith("a number"):  # 1 and 1.0 are one setting, with one key
                object.__setattr__(self, name, float(v))
        try:
            DepthDecoder.from_json(self.decoder)
        except (TypeError, ValueError, KeyError) as exc:
            raise ValueError(f"scan option decoder: {exc}") from None

    def to_json(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_json(d: object, where: str = "scan options") -> ScanOptions:
        """Options from JSON (a subset of the fields; the rest default); an unknown key or a bad value is an error
        naming it and ``where``."""
        if not isinstance(d, dict):
            raise ValueError(f"{where}: scan options are a JSON object, not {type(d).__name__}")
        unknown = sorted(set(d) - set(KNOBS) - {"decoder"})
        if unknown:
            raise ValueError(f"{where}: unknown scan option(s) {unknown}; known: decoder, {', '.join(KNOBS)}")
        try:
            return ScanOptions(**d)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None

    def updated(self, **changes) -> ScanOptions:
        """These options with ``changes`` (None values ignored), checked."""
        return self.merged({k: v for k, v in changes.items() if v is not None})

    def merged(self, changes: object, where: str = "scan options") -> ScanOptions:
        """These options with a JSON object of changes laid over them (a --scan-config file, a flow's ``scan``),
        checked; errors name ``where``."""
        if not isinstance(changes, dict):
            raise ValueError(f"{where}: scan options are a JSON object, not {type(changes).__name__}")
        return ScanOptions.from_json({**self.to_json(), **changes}, where)

    def scan_kwargs(self) -> dict:
        """``scan_recording``'s keyword arguments (every knob a recording's scan reads)."""
        return {k: getattr(self, k) for k in KNOBS if k not in DERIVE_KNOBS + CHECK_KNOBS}

    def alias(self) -> tuple[float, float, int]:
        """The stage's edge-alias rule by hits: (fraction, dominance, support)."""
        return (self.alias_fraction, self.alias_dominance, self.alias_support)

    def key(self) -> str:
        """Hash of what a recording's contribution depends on (the decoder and every knob but the stage's)."""
        d = {k: v for k, v in asdict(self).items() if k not in DERIVE_KNOBS + CHECK_KNOBS}
        return text_sha256(json.dumps(d, sort_keys=True), SCAN_VERSION)[:16]

    def changed(self) -> dict:
        """The knobs (and decoder) that differ from the defaults."""
        base = ScanOptions().to_json()
        return {k: v for k, v in self.to_json().items() if v != base[k]}

    def describe(self) -> str:
        """One line of what differs from the defaults ("the defaults" when nothing does)."""
        return ", ".join(f"{k}={json.dumps(v, sort_keys=True)}" for k, v in self.changed().items()) or "the defaults"

    @staticmethod
    def of_corpus(corpus: Path) -> ScanOptions:
        """The options of the corpus's last scan, else the defaults: what a scan given none uses."""
        return ScanOptions.stored(corpus) or ScanOptions()

    @staticmethod
    def stored(corpus: Path) -> ScanOptions | None:
        """The options of the corpus's last scan (``meta/scan.json``), or None before its first."""
        path = paths.meta(corpus, paths.SCAN)
        if not path.is_file():
            return None
        data = read_json(path, max_bytes=SCAN_CONFIG_MAX_BYTES)
        return ScanOptions.from_json(data, str(path))

    def store(self, corpus: Path) -> None:
        write_json(paths.meta(corpus, paths.SCAN), self.to_json())


SCAN_CONFIG_MAX_BYTES = 1 << 16
