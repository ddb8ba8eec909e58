"""Writing synthetic recordings in the public WildWorld layout, plus their truth side files.

``out_dir/<part>/<id>/{rgb.mp4, depth.mkv, state.csv, skeleton.npz}``, ``out_dir/<part>/skeleton_edges.json``
and ``out_dir/truth/<part>/<id>.{npz,json}`` (outside the WildWorld layout). See docs/formats.md,
"Synthetic recordings".
"""

from __future__ import annotations

import csv
import json
import os
from concurrent.futures import ProcessPoolExecutor
from datetime import UTC, datetime
from fractions import Fraction
from pathlib import Path

import av
import numpy as np

from marionette.geometry import matrix_to_quat, yaw_quat
from marionette.recordings.wildworld import DEPTH_FILE, RGB_FILE, SKELETON_FILE, STATE_FILE
from marionette.schema import load_rig
from terrain_scan.depth import SYNTHETIC_DEPTH_ENCODING, DepthDecoder

from . import behaviour, sim
from .cast import GREATSWORD, Cast, make_cast, rig_edges
from .clips import CLIPS, clip_table
from .render import Renderer, camera_pans, encode_depth, follow_camera, intrinsics

RECORDING_EPOCH = 1767225600  # 2026-01-01T00:00:00Z; recording k starts k days later
NPC_FIELDS = (
    "type_id",
    "member_id",
    "weapon_id",
    "pos",
    "rot",
    "motion_bank_id",
    "motion_id",
    "motion_frame",
    "hp",
    "max_hp",
    "red_hp",
    "sp",
    "max_sp",
    "atk",
    "wp_atk",
    "attr",
    "wp_attr",
    "crit_rate",
    "crit_atk_rate",
    "def",
    "resist_fire",
    "resist_water",
    "resist_ice",
    "resist_elec",
    "resist_dragon",
)
MONSTER_FIELDS = ("type_id", "pos", "rot", "motion_bank_id", "motion_id", "motion_frame", "hp", "max_hp", "cond")
COLUMNS = (
    ["camera.K", "camera.pos", "camera.rot", "npc.count", "npc.tracking"]
    + [f"npc.list.0.{f}" for f in NPC_FIELDS]
    + ["monster.count"]
    + [f"monster.list.0.{f}" for f in MONSTER_FIELDS]
)
RIGS = {"monster": "drake", "hunter": "hunter", "weapon": "greatsword"}


def _tuple(v, digits: int = 6) -> str:
    v = np.asarray(v, dtype=np.float64)
    if not np.isfinite(v).all():
        return "nan"
    return "(" + ", ".join(f"{x:.{digits}f}" for x in v) + ")"


def _num(v) -> str:
    if isinstance(v, str):
        return v
    if v is None or not np.isfinite(v):
        return "nan"
    return str(int(v)) if float(v).is_integer() else f"{float(v):.6f}"


def _atomic(path: Path, write) -> None:
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    os.replace(tmp, path)


def _hp(plan: sim.Plan, roots: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Hit points per frame: each attack that lands (targets within reach at its hit frame) takes damage."""
    N = plan.n_frames
    hp = {"hunter": np.full(N, 150.0), "monster": np.full(N, 2400.0)}
    for ent, other in (("hunter", "monster"), ("monster", "hunter")):
        for seg in plan.tracks[ent].segments:
            c = CLIPS[ent][seg.clip]
            if c.cls != "attack":
                continue
            f = seg.start + int(c.hit_at * c.length)
            if f < N and np.linalg.norm(roots[ent][f] - roots[other][f]) < behaviour.REACH[ent]:
                hp[other][f:] -= c.damage * (3.0 if other == "monster" else 0.3)  # the hunter's armour takes 70 %
    hp["hunter"] = np.maximum(hp["hunter"], 1.0)
    hp["monster"] = np.maximum(hp["monster"], 1.0)
    return hp


def _yuv420p_frame(rgb: np.ndarray) -> av.VideoFrame:
    """RGB (H, W, 3) uint8 → yuv420p frame, BT.601 limited range, converted in numpy.

    Converting here rather than in swscale keeps the encoded bitstream byte-stable between runs.
    """
    f = rgb.astype(np.float64)
    y = 16 + 0.257 * f[..., 0] + 0.504 * f[..., 1] + 0.098 * f[..., 2]
    u = 128 - 0.148 * f[..., 0] - 0.291 * f[..., 1] + 0.439 * f[..., 2]
    v = 128 + 0.439 * f[..., 0] - 0.368 * f[..., 1] - 0.071 * f[..., 2]
    H, W = y.shape
    frame = av.VideoFrame(W, H, "yuv420p")
    for plane, c in zip(
        frame.planes, (y, u.reshape(H // 2, 2, W // 2, 2).mean(axis=(1, 3)), v.reshape(H // 2, 2, W // 2, 2).mean(axis=(1, 3)))
    ):
        buf = np.zeros((c.shape[0], plane.line_size), np.uint8)
        buf[:, : c.shape[1]] = np.clip(np.round(c), 0, 255)
        plane.update(buf.tobytes())
    return frame


def _write_video(
    path: Path, frames, fps: int, codec: str, pix_fmt: str, fmt: str, options: dict, metadata: dict | None = None
) -> None:
    def write(tmp: Path) -> None:
        # bitexact: no random container ids or encoder version strings, so reruns are byte-identical.
        with av.open(str(tmp), "w", format=fmt, options={"fflags": "+bitexact"}) as c:
            c.metadata.update(metadata or {})
            s = c.add_stream(codec, rate=fps)
            s.width, s.height = frames[0].shape[1], frames[0].shape[0]
            s.pix_fmt = pix_fmt
            s.codec_context.thread_count = 1  # one thread: the bitstream is then byte-stable
            s.time_base = Fraction(1, fps)
            s.options = options
            for i, fr in enumerate(frames):
                vf = av.VideoFrame.from_ndarray(fr, format="gray") if fr.ndim == 2 else _yuv420p_frame(fr)
                vf.pts, vf.time_base = i, Fraction(1, fps)
                for p in s.encode(vf):
                    c.mux(p)
            for p in s.encode():
                c.mux(p)

    _atomic(path, write)


def write_recording(
    out_dir: Path,
    part: str,
    index: int,
    seed: int,
    seconds: float,
    width: int,
    height: int,
    fps: int,
    depth_mapping: dict | None = None,
    cast: dict | None = None,
    ray_threads: int = 0,
) -> Path:
    """Simulate, render and write one recording (its depth in ``depth_mapping``, a ``DepthDecoder`` JSON; default
    the game's ``SYNTHETIC_DEPTH_ENCODING``; who plays and where from ``make_cast(seed, **cast)``, default the drake, player 0
    and the greatsword on the first stage); ``ray_threads``: the renderer's (``Renderer``); returns its sample
    directory."""
    sample_id = f"rec{index:04d}"
    d = Path(out_dir) / part / sample_id
    d.mkdir(parents=True, exist_ok=True)
    N = int(round(seconds * fps))
    plan = sim.simulate(seed, index, N, float(fps))
    role = make_cast(seed, **(cast or {})).role(index)
    times = np.arange(N) / fps
    sk = sim.skeletons_at(plan, times, role)
    roots, yaws = {}, {}
    for ent in ("hunter", "monster"):
        roots[ent], yaws[ent], _ = sim.roots_at(plan, ent, times)
    present = np.ones(N, bool)
    present[plan.absent[0] : plan.absent[1]] = False
    cam_valid = np.ones(N, bool)
    cam_valid[plan.camera_invalid[0] : plan.camera_invalid[1]] = False
    pan = camera_pans(seed, index, N, float(fps)) if role.camera_pans else None
    cam_pos, cam_rot = follow_camera(roots["hunter"], yaws["hunter"], roots["monster"], present, pan)

    edges, radii = _bones(role)
    colours = role.skin.colours() if role.skin is not None else None
    renderer = Renderer(width, height, edges, radii, colours=colours, threads=ray_threads)
    encode = encode_depth if depth_mapping is None else DepthDecoder.from_json(depth_mapping).encode
    meshes = {e: renderer.meshes(e, sk[e]) for e in ("hunter", "weapon", "monster")}  # every frame's at once
    shown = {e: np.isfinite(sk[e]).all(axis=(1, 2)) for e in meshes}
    shown["monster"] &= present
    rgb, depth = [], []
    bodies = [{e: (V[i], T) for e, (V, T) in meshes.items() if shown[e][i]} for i in range(N)]
    for img, z in renderer.frames(cam_pos, cam_rot, bodies):
        rgb.append(img)
        depth.append(encode(z))
    # Rendered in the first stage's frame; what the recording states in world coordinates moves into its stage.
    stage = role.stage
    sk = {e: stage.points(v) for e, v in sk.items()}
    roots = {e: stage.points(v) for e, v in roots.items()}
    yaws = {e: v + stage.turn for e, v in yaws.items()} if not stage.identity else yaws
    cam_pos, cam_rot = stage.points(cam_pos), stage.rotations(cam_rot)
    if role.species is not None:  # the pos columns: each body's root joint
        roots["monster"] = sk["monster"][:, role.species.names.index(role.species.root)]
    if role.player.scale != 1.0:
        roots["hunter"] = sk["hunter"][:, load_rig("hunter").source_joints.index("pelvis")]
    _write_videos(d, rgb, depth, fps, index)

    K = intrinsics(width, height)
    rows = _state_rows(plan, role, roots, yaws, K, cam_pos, cam_rot, cam_valid, present)

    _atomic(d / STATE_FILE, lambda tmp: _write_csv(tmp, rows))

    m = sk["monster"].astype(np.float32)
    m[~present] = np.nan
    arrays = {
        f"m1_{role.monster_type}": m,
        f"n1_{role.player.type_id}": sk["hunter"].astype(np.float32),
        f"w1_{role.weapon.type_id}": sk["weapon"].astype(np.float32),
    }
    _atomic(d / SKELETON_FILE, lambda tmp: _savez(tmp, arrays))

    _write_truth(Path(out_dir) / "truth" / part, sample_id, roots, yaws, present, cam_valid, cam_pos, cam_rot)
    meta = _truth_meta(sample_id, part, seed, index, N, fps, width, height, depth_mapping, K, plan, cast, role)
    _atomic(Path(out_dir) / "truth" / part / f"{sample_id}.json", lambda tmp: tmp.write_text(json.dumps(meta, indent=1)))
    return d


def _truth_meta(
    sample_id: str,
    part: str,
    seed: int,
    index: int,
    N: int,
    fps: int,
    width: int,
    height: int,
    depth_mapping: dict | None,
    K,
    plan: sim.Plan,
    cast: dict | None,
    role,
) -> dict:
    """The truth side file's JSON: how the recording was made (seed, size, depth encoding, cast and role), the
    frames without a monster or a valid camera, the clip tables and each entity's played segments."""
    return {
        "sample_id": sample_id,
        "part": part,
        "seed": seed,
        "index": index,
        "n_frames": N,
        "fps": fps,
        "width": width,
        "height": height,
        "recording_time": RECORDING_EPOCH + 86400 * index,
        "depth_encoding": SYNTHETIC_DEPTH_ENCODING if depth_mapping is None else depth_mapping,
        "camera_K": list(K),
        "monster_absent_frames": list(plan.absent),
        "cast": cast or {},
        "role": role.to_json(),
        "camera_invalid_frames": list(plan.camera_invalid),
        "clips": {e: {str(k): v for k, v in clip_table(e).items()} for e in ("monster", "hunter")},
        "segments": {
            e: [{"start": s.start, "clip": s.clip, "length": s.length} for s in plan.tracks[e].segments]
            for e in ("monster", "hunter")
        },
    }


def _write_videos(d: Path, rgb: list[np.ndarray], depth: list[np.ndarray], fps: int, index: int) -> None:
    """rgb.mp4 (H.264) and depth.mkv (lossless HEVC, gray) of one recording, byte-stable across runs."""
    # One thread and no lookahead / macroblock tree: measured to make the bitstream byte-stable across runs.
    x264 = {
        "crf": "20",
        "preset": "veryfast",
        "x264-params": "threads=1:lookahead-threads=1:sync-lookahead=0:rc-lookahead=0:mbtree=0",
    }
    # the recording's time in the container (scanners read it; never the wall clock of the run)
    created = datetime.fromtimestamp(RECORDING_EPOCH + 86400 * index, UTC).strftime("%Y-%m-%dT%H:%M:%S.000000Z")
    _write_video(d / RGB_FILE, rgb, fps, "libx264", "yuv420p", "mp4", x264, {"creation_time": created})
    _write_video(
        d / DEPTH_FILE,
        depth,
        fps,
        "libx265",
        "gray",
        "matroska",
        {"x265-params": "lossless=1:log-level=error:pools=1:frame-threads=1"},
    )


def _write_csv(path: Path, rows: list[list[str]]) -> None:
    """state.csv: the header (``COLUMNS``) and the rows, "\\n"-terminated."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(COLUMNS)
        w.writerows(rows)


def _bones(role) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Each body's bones (edges) and capsule radii (m) as the cast's role draws them: its species' and weapon's own
    where they are not the built-in rigs, the drake's thick body and neck and tapering tail, the player's scale."""
    rigs = {e: load_rig(r) for e, r in RIGS.items()}
    edges = {e: rig_edges(r) for e, r in rigs.items()}
    if role.weapon != GREATSWORD:
        edges["weapon"] = np.asarray(role.weapon.edges, dtype=np.int64)
    radii = {}
    for e, r in rigs.items():
        if e == "monster" and role.species is not None:
            edges[e] = np.asarray(role.species.edges, dtype=np.int64)
            radii[e] = role.species.bone_radii()
            continue
        scale = np.ones(len(edges[e]))
        if e == "monster":  # a thick body and neck, a tapering tail
            child = [r.source_joints[c] for c in edges[e][:, 1]]
            scale = np.array(
                [
                    3.0
                    if n.startswith(("spine", "chest"))
                    else 2.0
                    if n.startswith(("neck", "head"))
                    else max(0.6, 2.2 - 0.17 * int(n[4:]))
                    if n.startswith("tail")
                    else 1.0
                    for n in child
                ]
            )
        radii[e] = r.capsule_radius_m * scale * (role.player.scale if e == "hunter" else 1.0)
    radii["weapon"] = radii["weapon"][: len(edges["weapon"])]
    return edges, radii


def _state_rows(
    plan: sim.Plan,
    role,
    roots: dict[str, np.ndarray],
    yaws: dict[str, np.ndarray],
    K,
    cam_pos: np.ndarray,
    cam_rot: np.ndarray,
    cam_valid: np.ndarray,
    present: np.ndarray,
) -> list[list[str]]:
    """The rows of state.csv (``COLUMNS``), one per frame: the camera, the player's fields, the monster's (NaN while it
    is away)."""
    N = len(present)
    hp = _hp(plan, roots)
    cam_q = matrix_to_quat(cam_rot)
    hq, mq = yaw_quat(yaws["hunter"]), yaw_quat(yaws["monster"])
    hnames, hmf = sim.clip_at_frames(plan, "hunter", np.arange(N))
    mnames, mmf = sim.clip_at_frames(plan, "monster", np.arange(N))
    rows = []
    for i in range(N):
        hc, mc = CLIPS["hunter"][hnames[i]], CLIPS["monster"][mnames[i]]
        row = [_tuple(K), _tuple(cam_pos[i]), _tuple(cam_q[i], 8)] if cam_valid[i] else ["nan"] * 3
        row += ["1", "0"]
        npc = {
            "type_id": role.player.type_id,
            "member_id": 0,
            "weapon_id": role.weapon.type_id,
            "pos": _tuple(roots["hunter"][i]),
            "rot": _tuple(hq[i], 8),
            "motion_bank_id": hc.bank,
            "motion_id": hc.motion,
            "motion_frame": int(hmf[i]),
            "hp": hp["hunter"][i],
            "max_hp": 150,
            "red_hp": min(150.0, hp["hunter"][i] + 10.0),
            "sp": 100,
            "max_sp": 100,
            "atk": 220,
            "wp_atk": 1150,
            "attr": 0,
            "wp_attr": 2,
            "crit_rate": 0.15,
            "crit_atk_rate": 1.25,
            "def": 180,
            "resist_fire": 3,
            "resist_water": 0,
            "resist_ice": -2,
            "resist_elec": 1,
            "resist_dragon": 0,
        }
        row += [_num(npc[f]) if not isinstance(npc[f], str) else npc[f] for f in NPC_FIELDS]
        if present[i]:
            frac = hp["monster"][i] / 2400.0
            cond = "angry" if frac < 0.7 else "tired" if mc.cls == "stationary" and frac < 0.9 else "none"
            mon = {
                "type_id": role.monster_type,
                "pos": _tuple(roots["monster"][i]),
                "rot": _tuple(mq[i], 8),
                "motion_bank_id": mc.bank,
                "motion_id": mc.motion,
                "motion_frame": int(mmf[i]),
                "hp": hp["monster"][i],
                "max_hp": 2400,
                "cond": cond,
            }
            row += ["1"] + [_num(mon[f]) if not isinstance(mon[f], str) else mon[f] for f in MONSTER_FIELDS]
        else:
            row += ["0"] + ["nan"] * len(MONSTER_FIELDS)
        rows.append(row)
    return rows


def _write_truth(
    tdir: Path,
    sample_id: str,
    roots: dict[str, np.ndarray],
    yaws: dict[str, np.ndarray],
    present: np.ndarray,
    cam_valid: np.ndarray,
    cam_pos: np.ndarray,
    cam_rot: np.ndarray,
) -> None:
    """The truth side file's arrays (``truth/<part>/<sample>.npz``): headings, world roots, presence and the camera."""
    tdir.mkdir(parents=True, exist_ok=True)
    truth = {
        "heading_monster": yaws["monster"],
        "heading_hunter": yaws["hunter"],
        "root_world_monster": roots["monster"],
        "root_world_hunter": roots["hunter"],
        "monster_present": present,
        "camera_valid": cam_valid,
        "camera_pos_world": cam_pos,
        "camera_rot_cw": cam_rot,
    }
    _atomic(tdir / f"{sample_id}.npz", lambda tmp: _savez(tmp, truth))


def _savez(tmp: Path, arrays: dict) -> None:
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


def write_edges(out_dir: Path, part: str, cast: Cast | None = None) -> Path:
    """``<part>/skeleton_edges.json``: edges key → [[parent, child], ...] in source joint indices, for every
    skeleton type of ``cast`` (default: the drake, the player, the greatsword)."""
    path = Path(out_dir) / part / "skeleton_edges.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    data = (cast or Cast()).edges()
    _atomic(path, lambda tmp: tmp.write_text(json.dumps(data)))
    return path


def generate(
    out_dir,
    recordings: int = 2,
    seconds: float = 20.0,
    seed: int = 0,
    width: int = 320,
    height: int = 180,
    fps: int = 30,
    part: str = "data_part1",
    workers: int = 1,
    hidden_depth: bool = False,
    species: int = 0,
    players: int = 1,
    weapons: int = 1,
    stages: int = 1,
    skins: bool = False,
    camera_pans: bool = False,
) -> list[Path]:
    """Write ``recordings`` synthetic recordings of ``seconds`` s each (in ``workers`` processes);
    returns the sample directories. Each recording depends only on (seed, index), never on ``workers``.
    With ``hidden_depth`` the game encodes depth with a mapping drawn from a family by ``seed``
    (``hidden_depth_mapping``), written only to the truth, as WildWorld does not publish its own. ``species``,
    ``players``, ``weapons`` and ``stages`` size the cast (``cast.make_cast``; recording k plays ``role(k)``); with
    ``skins`` each recording's monster and player have colours of their own (``cast.draw_skin``); with
    ``camera_pans`` the player looks around now and then (``render.camera_pans``)."""
    out_dir = Path(out_dir)
    spec = {"species": species, "players": players, "weapons": weapons, "stages": stages}
    spec = {k: v for k, v in spec.items() if v != (0 if k == "species" else 1)}
    if skins:
        spec["skins"] = True
    if camera_pans:
        spec["camera_pans"] = True
    write_edges(out_dir, part, make_cast(seed, **spec))
    mapping = hidden_depth_mapping(seed) if hidden_depth else None
    pooled = workers > 1 and recordings > 1  # one recording per process: each casts its rays on one thread
    args = [(out_dir, part, k, seed, seconds, width, height, fps, mapping, spec or None, int(pooled)) for k in range(recordings)]
    if not pooled:
        return [write_recording(*a) for a in args]

    with ProcessPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(write_recording, *zip(*args)))


def hidden_depth_mapping(seed: int) -> dict:
    """A depth mapping of the family real games use, drawn by ``seed``: the code affine in inverse depth (a
    perspective depth buffer) or in log depth, near plane 1–3 m, far plane 150–500 m (``DepthDecoder`` JSON)."""
    rng = np.random.default_rng([seed, 0xDE7])
    kind = ("inverse", "log")[int(rng.integers(2))]
    return {"kind": kind, "z_near": round(float(rng.uniform(1.0, 3.0)), 3), "z_far": round(float(rng.uniform(150.0, 500.0)), 1)}


def load_truth(out_dir, part: str, sample_id: str) -> dict:
    """The truth of one synthetic recording: headings, roots, clips, spans, recording time, depth encoding."""
    tdir = Path(out_dir) / "truth" / part
    meta = json.loads((tdir / f"{sample_id}.json").read_text())
    with np.load(tdir / f"{sample_id}.npz", allow_pickle=False) as z:
        arr = {k: z[k] for k in z.files}
    meta["clips"] = {e: {int(k): v for k, v in t.items()} for e, t in meta["clips"].items()}
    return {
        **meta,
        "heading": {"monster": arr["heading_monster"], "hunter": arr["heading_hunter"]},
        "root_world": {"monster": arr["root_world_monster"], "hunter": arr["root_world_hunter"]},
        "monster_present": arr["monster_present"],
        "camera_valid": arr["camera_valid"],
        "camera_pos_world": arr["camera_pos_world"],
        "camera_rot_cw": arr["camera_rot_cw"],
    }


def world_skeletons_at(out_dir, part: str, sample_id: str, times_s) -> dict[str, np.ndarray]:
    """Analytic world source skeletons (float64) at times (s from frame 0), re-simulated from the seed."""
    meta = json.loads((Path(out_dir) / "truth" / part / f"{sample_id}.json").read_text())
    plan = sim.simulate(meta["seed"], meta["index"], meta["n_frames"], float(meta["fps"]))
    role = make_cast(meta["seed"], **meta.get("cast", {})).role(meta["index"])
    return {e: role.stage.points(v) for e, v in sim.skeletons_at(plan, times_s, role).items()}
