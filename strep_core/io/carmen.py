"""CARMEN laser logs (``.log`` or ``.log.gz``), as used by the classic 2D SLAM data sets.

Only ``FLASER`` lines are read::

    FLASER n r_0 ... r_{n-1} x y theta odom_x odom_y odom_theta timestamp host logger_timestamp

* ``r_i`` are ranges in metres; beam ``i`` is at angle ``-pi/2 + i * step`` (radians,
  counter-clockwise, 0 = ahead), the start and step CARMEN's own parser gives an ``FLASER``
  line (``carmen_laser_guess_angle_increment``): 1 degree for 180 or 181 beams, 0.5 for 360 or
  361, 0.25 for 400 or 401, otherwise ``pi / (n - 1)``. A SICK's 180 beams thus end at +89
  degrees; spacing them ``pi / 179`` stretches every bearing by 0.56 %, which the local SLAM
  turns into a heading drift (docs/design/laser-slam.md, rounds 4 and 5).
* ``x y theta`` is the laser pose corrected by a SLAM system: the ground truth here.
* ``odom_x odom_y odom_theta`` is the raw odometry: the initial guess (``initial_poses``).
  "Corrected" logs such as intel and aces overwrite it with the corrected pose on every
  line; then it is no guess at all but the ground truth, and ``initial_poses`` is ``None``
  (``meta["odometry"]`` says so).

Invalid ranges (no return) are dropped: ``r <= 0``, non-finite, and ``r >= limit`` where
``limit`` is ``max_range`` when given; otherwise ``limit = min(80 m, sentinel)``, with
``sentinel`` the smallest reading within 5 % of the log's largest whose exact value repeats in
at least 0.1 % of all readings (a saturated "no return" code, e.g. 81.83 in intel, 50.00 in
aces, 51.15 in acapulco and edmonton, 51.06 in infinite-corridor: real ranges vary
continuously and do not pile up on one value). The code need not be the largest reading:
acapulco's largest is 51.25 (a few), its 51.15 makes 6 % of its readings, and an arc of them
at the same range in every scan holds the matcher at zero motion (docs/design/laser-slam.md).
"""

from __future__ import annotations

import io
import lzma
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from strep_core import geometry as g
from strep_core.errors import FormatError, SequenceError
from strep_core.io.limits import ReadBudget, open_decompressed
from strep_core.sequence import FrameSelection, Sequence

__all__ = ["DEFAULT_MAX_RANGE", "SENTINEL_SHARE", "read_carmen"]

DEFAULT_MAX_RANGE = 80.0  # metres: SICK LMS maximum; readings at or beyond mean no return
SENTINEL_SHARE = 1e-3  # a top reading repeated in >= this share of readings is a no-return code
SENTINEL_TOP = 0.95  # no-return codes sit within 5 % of the log's largest reading
MAX_LINE_CHARS = 1 << 20  # a FLASER line of thousands of beams is some 10 kB


def _lines(path: Path, budget: ReadBudget) -> Iterator[tuple[int, str]]:
    """``(line number, line)`` of the log, streamed (gunzipped when it is gzip, whatever its
    name), every byte charged to ``budget``; a line longer than `MAX_LINE_CHARS` is refused."""
    lineno = 0
    try:
        with io.TextIOWrapper(open_decompressed(path, budget), encoding="utf-8") as text:
            while line := text.readline(MAX_LINE_CHARS + 1):
                lineno += 1
                if len(line) > MAX_LINE_CHARS:
                    raise FormatError(f"{path}:{lineno}: a line longer than {MAX_LINE_CHARS} characters")
                yield lineno, line
    except (OSError, EOFError, zlib.error, lzma.LZMAError) as exc:
        raise FormatError(f"{path}: cannot read CARMEN log ({exc})") from exc
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: not a text CARMEN log ({exc.reason} near line {lineno + 1})") from exc


def beam_step(n: int) -> float:
    """The angle between two beams of an ``n``-beam ``FLASER`` line, as CARMEN reads it."""
    for beams, degrees in (((180, 181), 1.0), ((360, 361), 0.5), ((400, 401), 0.25)):
        if n in beams:
            return float(np.radians(degrees))
    return float(np.pi / (n - 1))


def _parse_flaser(tokens: list[str], where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ranges ``(n,)``, laser pose ``(3,)`` and odometry ``(3,)`` of one FLASER line."""
    try:
        n = int(tokens[1])
    except (IndexError, ValueError) as exc:
        raise FormatError(f"{where}: FLASER line without a beam count") from exc
    if n < 2:
        raise FormatError(f"{where}: FLASER line with {n} beams; at least 2 are needed")
    need = 2 + n + 6
    if len(tokens) < need:
        raise FormatError(
            f"{where}: FLASER line has {len(tokens) - 2} numbers after the count {n}; "
            f"expected at least {n + 6} ({n} ranges, laser x y theta, odometry x y theta)"
        )
    try:
        vals = np.array(tokens[2:need], dtype=np.float64)
    except ValueError as exc:
        raise FormatError(f"{where}: FLASER line holds a value that is not a number ({exc})") from exc
    return vals[:n], vals[n : n + 3], vals[n + 3 : n + 6]


def read_carmen(
    path: str | Path,
    *,
    frames: str | FrameSelection | None = None,
    max_range: float | None = None,
    budget: ReadBudget | None = None,
) -> Sequence:
    """Read the ``FLASER`` scans of a CARMEN log as a 2D sequence in metres.

    Args:
        path: a ``.log`` file, gzipped or not.
        frames: ``start:stop[:step]`` over the scans; original indices are kept.
        max_range: ranges at or beyond this (metres) are dropped; default: see the module
            docstring (80 m, or the log's repeated maximum when smaller).
        budget: the bytes the log may inflate to and the range readings it may hold
            (default: the library's limits).

    Returns:
        A `Sequence` with ``K`` frames ``(N_i, 2)`` in the laser frame (metres), ``poses``
        ``(K, 3, 3)`` from the corrected laser poses and ``initial_poses`` from odometry
        (``None`` when the odometry equals the corrected poses on every line).

    Raises:
        FormatError: unreadable file, no FLASER line, a malformed FLASER line.
        SequenceError: a selected scan keeps fewer than 3 valid ranges, or non-finite poses.
    """
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: no such CARMEN log")
    budget = budget or ReadBudget()
    scans = []
    for lineno, line in _lines(path, budget):
        tokens = line.split()
        if tokens and tokens[0] == "FLASER":
            scans.append(_parse_flaser(tokens, f"{path}:{lineno}"))
            budget.take_points(len(scans[-1][0]), f"{path}:{lineno}")
    if not scans:
        raise FormatError(f"{path}: no FLASER lines (not a CARMEN laser log?)")

    all_ranges = np.concatenate([s[0] for s in scans])
    if max_range is not None:
        limit, rule = float(max_range), "max_range"
    else:
        limit, rule = DEFAULT_MAX_RANGE, "default"
        finite = all_ranges[np.isfinite(all_ranges)]
        if finite.size:
            high = finite[finite >= SENTINEL_TOP * float(finite.max())]
            values, counts = np.unique(high, return_counts=True)
            codes = values[counts >= max(2, SENTINEL_SHARE * finite.size)]
            if codes.size and float(codes.min()) < limit:
                limit, rule = float(codes.min()), "sentinel"

    sel = FrameSelection.parse(frames).keep(len(scans))
    pts, gt, odom = [], [], []
    for i in sel:
        r, pose, od = scans[i]
        angles = -np.pi / 2 + np.arange(len(r)) * beam_step(len(r))
        ok = np.isfinite(r) & (r > 0) & (r < limit)
        pts.append(np.stack([r[ok] * np.cos(angles[ok]), r[ok] * np.sin(angles[ok])], 1))
        gt.append(pose)
        odom.append(od)
    gt_poses = g.se2_from_xytheta(np.asarray(gt).reshape(-1, 3))
    odom_poses: np.ndarray | None = g.se2_from_xytheta(np.asarray(odom).reshape(-1, 3))
    # "Corrected" logs (intel, aces...) overwrite odometry with the corrected pose: an
    # initial guess equal to the ground truth would make every benchmark meaningless.
    odometry_is_corrected = all(np.array_equal(s[1], s[2]) for s in scans)
    if odometry_is_corrected:
        odom_poses = None
    try:
        return Sequence(
            frames=pts,
            name=path.name.removesuffix(".gz").removesuffix(".log"),
            unit="m",
            poses=gt_poses,
            initial_poses=odom_poses,
            indices=sel,
            meta={
                "source": str(path),
                "format": "carmen",
                "max_range": limit,
                "max_range_rule": rule,
                "beams": len(scans[0][0]),
                "sensor": {"kind": "laser", "planar": True, "fov_deg": 180.0},
                "odometry": "equal to the corrected poses; not used" if odometry_is_corrected else "raw",
            },
        )
    except SequenceError as exc:
        raise SequenceError(f"{path}: {exc}") from exc
