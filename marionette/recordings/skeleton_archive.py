"""A recording's skeleton.npz, read member by member: the zip directory and each .npy header are checked against the
limits before a member is inflated, and only the members asked for are read."""

from __future__ import annotations

import math
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from marionette.recordings.errors import SampleError, regular_input

MAX_MEMBER_BYTES = 2 << 30  # default cap on one inflated skeleton.npz member (IngestOptions.max_member_bytes)
MAX_JOINTS = 1024  # no rig comes near this; a member declaring more joints is refused unread
_NPY_HEADER_ROOM = 64 << 10  # bytes an .npy member may hold besides its array (magic + header)

# what reading a damaged zip member can raise (RuntimeError: encrypted; NotImplementedError: unknown compression)
# what a damaged archive or .npy header raises (numpy parses the header as a Python literal: SyntaxError, TokenError)
_ZIP_ERRORS = (
    zipfile.BadZipFile,
    zlib.error,
    ValueError,
    OSError,
    EOFError,
    RuntimeError,
    NotImplementedError,
    SyntaxError,
    tokenize.TokenError,
    TypeError,
    KeyError,
)


class SkeletonArchive:
    """A skeleton.npz read member by member: the zip directory and each .npy header are checked against
    the limits before a member is inflated, and only the members asked for are read."""

    def __init__(self, path: Path, max_member_bytes: int = MAX_MEMBER_BYTES):
        self.path = Path(path)
        self.max_member_bytes = int(max_member_bytes)
        if not self.path.exists():
            raise SampleError(f"{self.path}: missing")
        regular_input(self.path)
        try:
            with self._open() as z:
                self._members = {i.filename[:-4]: i for i in z.infolist() if i.filename.endswith(".npy")}
        except SampleError:
            raise
        except _ZIP_ERRORS as exc:
            raise SampleError(f"{self.path}: unreadable, truncated or corrupt ({type(exc).__name__}: {exc})") from None

    @property
    def keys(self) -> list[str]:
        """Member names without ``.npy``, as ``numpy.load`` lists them."""
        return sorted(self._members)

    def __contains__(self, key: str) -> bool:
        return key in self._members

    def _open(self) -> zipfile.ZipFile:
        try:
            return zipfile.ZipFile(self.path)
        except _ZIP_ERRORS as exc:
            raise SampleError(f"{self.path}: unreadable, truncated or corrupt ({type(exc).__name__}: {exc})") from None

    def _bad(self, key: str, exc: BaseException) -> SampleError:
        return SampleError(f"{self.path}: member {key}.npy unreadable, truncated or corrupt ({type(exc).__name__}: {exc})")

    @staticmethod
    def _read_header(fh) -> tuple[tuple[int, ...], np.dtype, bool]:  # noqa: ANN001 — a zip member stream
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise ValueError(f"unsupported .npy format version {version}")
        return tuple(int(x) for x in shape), np.dtype(dtype), bool(fortran)

    def header(self, key: str) -> tuple[tuple[int, ...], np.dtype]:
        """(shape, dtype) a member declares, read from its .npy header without inflating the array."""
        try:
            with self._open() as z, z.open(self._members[key]) as fh:
                shape, dtype, _ = self._read_header(fh)
        except SampleError:
            raise
        except _ZIP_ERRORS as exc:
            raise self._bad(key, exc) from None
        return shape, dtype

    def read(self, key: str, max_frames: int | None = None) -> np.ndarray:
        """One member as an array. Only its .npy header is read before it must declare a float (N, J, 3) array
        with N ≤ ``max_frames`` and J ≤ MAX_JOINTS of at most ``max_member_bytes`` bytes, and the zip directory
        the same size; otherwise SampleError, and nothing is inflated."""
        info = self._members[key]
        cap = self.max_member_bytes
        try:
            with self._open() as z, z.open(info) as fh:
                shape, dtype, fortran = self._read_header(fh)  # a few hundred bytes: numpy caps the header
                head = fh.tell()
                nbytes = math.prod(shape) * dtype.itemsize  # Python ints: a huge declared shape cannot overflow
                described = f"{self.path}: member {key}.npy declares shape {shape} {dtype.str} ({nbytes:,} bytes)"
                if dtype.kind != "f" or len(shape) != 3 or shape[2] != 3 or shape[1] > MAX_JOINTS:
                    raise SampleError(f"{described}: expected a float (N, J, 3) array with J ≤ {MAX_JOINTS}; not inflated")
                if max_frames is not None and shape[0] > max_frames:
                    raise SampleError(f"{described}: more than the {max_frames} frames the sample can need; not inflated")
                if nbytes > cap:
                    raise SampleError(f"{described}: over the per-member cap of {cap:,} bytes (max_member_bytes); not inflated")
                if info.file_size > cap + _NPY_HEADER_ROOM:
                    raise SampleError(
                        f"{described}, but the zip directory gives it {info.file_size:,} bytes uncompressed, over the "
                        f"per-member cap of {cap:,} bytes (max_member_bytes); not inflated"
                    )
                if info.file_size != head + nbytes:
                    raise SampleError(
                        f"{described}, but the zip directory gives it {info.file_size:,} bytes ({head} of them header): "
                        "not an .npy file numpy wrote"
                    )
                raw = np.empty(nbytes, np.uint8)
                got = 0
                while got < nbytes:  # in pieces: reading it whole would hold the data twice
                    piece = fh.read(min(16 << 20, nbytes - got))
                    if not piece:
                        raise SampleError(f"{described}, but its data ends after {got:,} bytes (truncated)")
                    raw[got : got + len(piece)] = np.frombuffer(piece, np.uint8)
                    got += len(piece)
                fh.read(1)  # reaching the end makes zipfile check the member's CRC
        except SampleError:
            raise
        except _ZIP_ERRORS as exc:
            raise self._bad(key, exc) from None
        return raw.view(dtype).reshape(shape, order="F" if fortran else "C")


def load_skeletons(
    path: Path, keys: list[str] | None = None, max_frames: int | None = None, max_member_bytes: int = MAX_MEMBER_BYTES
) -> dict[str, np.ndarray]:
    """The named arrays (default: all) of a skeleton.npz, each checked before it is inflated (``SkeletonArchive``)."""
    archive = SkeletonArchive(path, max_member_bytes)
    return {k: archive.read(k, max_frames) for k in (archive.keys if keys is None else keys)}
