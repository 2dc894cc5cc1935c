"""The ``strep`` command line: parses options, calls the library, prints results.

It sits above both the core and the service (`docs/design/extending.md`): `strep_core`,
`strep_bench` and `app` are imported lazily, per command, so ``strep --help`` stays fast.
Library code raises typed errors (`strep_core.errors`); here they become a one-line message
on stderr and a non-zero exit code, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence as Seq
from pathlib import Path
from typing import Any, get_args

from strep_cli.progress import ProgressMode
from strep_cli.progress import ProgressSink as _ProgressSink
from strep_core.config import DeviceName, InitName, ProfileName, StartName
from strep_core.errors import StrepError

EXIT_ERROR = 2
EXIT_INTERRUPTED = 130


def _set_dotted(data: dict[str, Any], key: str, value: Any) -> None:
    parts = key.split(".")
    node = data
    for p in parts[:-1]:
        node = node.setdefault(p, {})
        if not isinstance(node, dict):
            raise StrepError(f"--set {key}: {p} is not a section")
    node[parts[-1]] = value


def _parse_value(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def build_config(args: argparse.Namespace) -> Any:
    """RunConfig from ``--config FILE``, then the named options, then ``--set key=value``."""
    from strep_core.config import RunConfig

    base: dict[str, Any] = RunConfig.load(args.config).model_dump() if args.config else {}
    named = {
        "method": args.method,
        "seed": args.seed,
        "frames": args.frames,
        "init": args.init,
        "start": args.start,
        "device": args.device,
        "threads": args.threads,
        "from_model": str(args.from_model) if args.from_model else None,
        "profile": args.profile,
    }
    if args.init is not None and args.start is None:
        base.pop("start", None)  # a config file's resolved start yields to a new --init
    base.update({k: v for k, v in named.items() if v is not None})
    if args.freeze:
        base["freeze"] = True
    if args.iterations is not None:
        _set_dotted(base, "optim.iterations", args.iterations)
    for item in args.set or []:
        if "=" not in item:
            raise StrepError(f"--set {item!r}: expected KEY=VALUE, e.g. optim.iterations=200")
        key, value = item.split("=", 1)
        _set_dotted(base, key.strip(), _parse_value(value))
    if base.get("freeze") and not base.get("from_model"):
        raise StrepError("--freeze needs --from-model FILE")
    return RunConfig.build(**base)


def _fmt(value: Any, unit: str = "") -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.3f}{unit}"
    return f"{value}{unit}"


def _accepted_inputs() -> str:
    from strep_core.io import FORMATS

    return "sample:NAME, " + ", ".join(f"{f.name} ({' '.join(f.extensions)})" for f in FORMATS)


def _single_cloud(source: str) -> Path | None:
    """``source`` when it is one PLY/PCD file (one frame, not a sequence), else None."""
    path = Path(source)
    return path if path.is_file() and path.suffix.lower() in (".ply", ".pcd") else None


def _check_output(path: Path, what: str, *, folder: bool) -> None:
    """Refuse, before the run, an output path that cannot be written: ``--out`` naming a file,
    ``--rrd`` naming a folder, or a parent that is a file or not writable."""
    if path.exists() and path.is_dir() != folder:
        kind = "a file" if folder else "a folder"
        raise StrepError(f"{what} {path}: is {kind}; give {'a folder' if folder else 'a file name'}")
    if not folder and not path.parent.is_dir():  # a file goes into a folder that exists: no silent mkdir
        raise StrepError(f"{what} {path}: the folder {path.parent} does not exist")
    parent = path if folder and path.exists() else path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise StrepError(f"{what} {path}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise StrepError(f"{what} {path}: {parent} is not writable")


def _check_early(config: Any) -> None:
    """What can fail without the data: the method's name, the device asked for."""
    from strep_core.methods import get
    from strep_core.resolve import resolve_device

    get(config.method)
    resolve_device(config.device)


def cmd_run(args: argparse.Namespace) -> int:
    from strep_core.runner import run_input

    if cloud := _single_cloud(args.input):
        raise StrepError(
            f"{cloud}: a single point cloud is one frame, and registration needs a sequence of 2 or more; "
            f"give a folder of PLY/PCD frames or one of {_accepted_inputs()}"
        )
    config = build_config(args)
    _check_early(config)  # an unknown method or a missing GPU fails before any loading
    out_dir = Path(args.out)
    _check_output(out_dir, "--out", folder=True)  # before the run, not after it
    if args.rrd is not None:
        _check_output(args.rrd, "--rrd", folder=False)
    mode: ProgressMode = "off" if args.quiet else "bar" if (sys.stderr.isatty() or args.progress) else "lines"
    sink = _ProgressSink(mode, config.method)

    def recording(scene: Any) -> list[Any]:
        """``--rrd``: a Rerun recording of the run (the sink lives in app/, imported only when asked)."""
        import uuid

        from app.rrd import cli_sink

        return [cli_sink(args.rrd, scene, config.method, f"cli-{uuid.uuid4().hex[:12]}")]

    try:
        result = run_input(args.input, config, out_dir=out_dir, sink=sink, sinks=recording if args.rrd else None)
    finally:
        sink.close()
    m = result.metrics
    unit = f" {m['unit']}"
    print(
        f"{m['method']} on {m['sequence']}: {m['frames']} frames, ATE {_fmt(m['ate'], unit)}, "
        f"point L2 {_fmt(m['point_l2'], unit)}, {m['wall_seconds']:.1f} s "
        f"(init: {m['initial_guess']}, ATE {_fmt(m.get('initial_ate'), unit)}) -> {out_dir}"
        + (f", {args.rrd}" if args.rrd is not None else "")
    )
    return 0


def cmd_generate(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if args.kind == "2d":
        from strep_core.sim.lidar2d import simulate_2d, write_deepmapping

        seq = simulate_2d(args.seed, frames=args.frames or 256, noise=args.noise)
    else:
        from strep_core.sim.depth3d import simulate_3d

        seq = simulate_3d(args.seed, frames=args.frames or 16, noise=args.noise)
    if args.format == "deepmapping":
        if seq.dim != 2:
            raise StrepError("--format deepmapping is a 2D format; use npz for 3D")
        write_deepmapping(seq, out)
        target = out
    else:
        from strep_core.io.npz import write_npz

        out.mkdir(parents=True, exist_ok=True)
        target = out / f"{seq.name}.npz"
        write_npz(seq, target)
    print(f"wrote {seq.name}: {len(seq)} frames, {seq.num_points} points ({seq.unit}) -> {target}")
    return 0


def cmd_samples(args: argparse.Namespace) -> int:
    from strep_core.samples import list_samples

    for s in list_samples():
        print(f"sample:{s.name:<14} {s.dims}D {s.frames:>4} frames {s.points:>7} points  {s.description}")
    return 0


def cmd_methods(args: argparse.Namespace) -> int:
    from strep_core.methods import available

    for name, info in available().items():
        kind = "learned" if info.learned else "classical"
        print(f"{name:<14} {kind:<10} {info.description}")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from strep_core.runner import load_input

    if cloud := _single_cloud(args.input):  # one frame: described, though no method registers it alone
        from strep_core.io.folder import read_point_cloud

        pts = read_point_cloud(cloud).points
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        info = {"name": cloud.name, "frames": 1, "dims": int(pts.shape[1]), "points": len(pts)}
        info |= {"extent": [round(float(v), 6) for v in hi - lo], "has_ground_truth": False}
        info["note"] = "one point cloud: `strep run` needs a sequence of 2 or more frames (a folder of PLY/PCD frames)"
        print(json.dumps(info, indent=2))
        return 0
    seq = load_input(args.input, frames=args.frames)
    print(json.dumps({**seq.summary(), "scale": round(seq.scale(), 6)}, indent=2))
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from strep_bench.bench import main as bench_main

    if args.executor != "ray":
        return bench_main(args)
    from strep_bench.ray_runner import run_cases_ray  # Ray is imported only when asked

    def runner(cases: list[Any], methods: list[str], quick: bool) -> list[dict[str, Any]]:
        return run_cases_ray(cases, methods, quick, address=args.ray_address or "local", cpus=args.ray_cpus)

    return bench_main(args, runner=runner)


def cmd_reproduce(args: argparse.Namespace) -> int:
    from strep_bench.reproduce import main as reproduce_main

    return reproduce_main(args)


def cmd_serve(args: argparse.Namespace) -> int:
    from app.server import serve

    return serve(host=args.host, port=args.port, data_dir=args.data_dir, viewer_port=args.viewer_port)


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="strep",
        description="Unsupervised global registration of temporal sequences of 2D/3D point clouds (STREP).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="register a sequence and write trajectory, map and metrics")
    run.add_argument("input", help="a file or folder in a supported format (see `strep info`), or sample:NAME")
    run.add_argument("--method", "-m", help="registration method (see `strep methods`); default strep")
    run.add_argument("--out", "-o", default="runs/latest", help="output folder (default runs/latest)")
    run.add_argument("--frames", help="frame selection start:stop[:step]")
    run.add_argument("--seed", type=int)
    run.add_argument("--iterations", type=int, help="optimiser iterations (learned methods)")
    run.add_argument(
        "--start",
        choices=get_args(StartName),
        help="learned methods: scratch (from identity, no classical step: the paper's setting) or pose-graph "
        "(refine the multiway pose graph); auto: scratch if --init identity, else pose-graph",
    )
    run.add_argument(
        "--init",
        choices=get_args(InitName),
        help="initial guess (auto: odometry if present else identity; learned methods add a pose-graph warm start "
        "unless --start scratch)",
    )
    run.add_argument(
        "--profile",
        choices=get_args(ProfileName),
        help="settings for this kind of data (default auto: a probe of a few frame pairs picks one)",
    )
    run.add_argument("--device", choices=get_args(DeviceName))
    run.add_argument("--threads", type=int, help="CPU threads for torch (default: all cores)")
    run.add_argument("--config", type=Path, help="a config.json to start from")
    run.add_argument("--set", action="append", metavar="KEY=VALUE", help="any config field, e.g. loss.window=3")
    run.add_argument("--from-model", type=Path, help="a model.pt saved by an earlier learned run")
    run.add_argument("--freeze", action="store_true", help="with --from-model: re-optimise only the latents")
    run.add_argument("--quiet", "-q", action="store_true", help="no progress at all (only the final line)")
    run.add_argument(
        "--progress",
        action="store_true",
        help="a progress bar even when stderr is not a terminal (else one line per stage there)",
    )
    run.add_argument("--rrd", type=Path, metavar="FILE", help="also record the run into a Rerun recording (.rrd)")
    run.set_defaults(fn=cmd_run)

    gen = sub.add_parser("generate", help="simulate a sequence (2D lidar or 3D depth)")
    gen.add_argument("kind", choices=["2d", "3d"])
    gen.add_argument("--out", "-o", required=True)
    gen.add_argument("--seed", type=int, default=0)
    gen.add_argument("--frames", type=int)
    gen.add_argument("--noise", type=float, default=0.0, help="range/depth noise (sequence unit)")
    gen.add_argument("--format", choices=["npz", "deepmapping"], default="npz")
    gen.set_defaults(fn=cmd_generate)

    sub.add_parser("samples", help="list the bundled sample sequences").set_defaults(fn=cmd_samples)
    sub.add_parser("methods", help="list the registration methods").set_defaults(fn=cmd_methods)

    info = sub.add_parser("info", help="describe a sequence")
    info.add_argument("input")
    info.add_argument("--frames")
    info.set_defaults(fn=cmd_info)

    bench = sub.add_parser("bench", help="benchmark every method on the standard sequences")
    bench.add_argument("--quick", action="store_true", help="a few minutes: fewer sequences and iterations")
    bench.add_argument("--out", "-o", default="bench_out", help="folder for the JSON and the table")
    bench.add_argument("--methods", help="comma-separated subset of methods")
    bench.add_argument("--suites", help="comma-separated subset of suites")
    bench.add_argument("--data", type=Path, help="folder of the shared real data (default ../shared/data)")
    bench.add_argument("--docs", type=Path, help="also write the table into this markdown file")
    bench.add_argument(
        "--start",
        choices=["pose-graph", "scratch"],
        default="pose-graph",
        help="how the learned methods start: refine the pose graph, or from identity with no classical step",
    )
    bench.add_argument(
        "--executor",
        choices=["local", "ray"],
        default="local",
        help="local: one run after another here; ray: every (sequence, method) run as a Ray task (needs the ray extra)",
    )
    bench.add_argument(
        "--ray-address",
        default=os.environ.get("STREP_RAY_ADDRESS", "local"),
        help="with --executor ray: local (start a runtime here), auto (the running cluster) or a cluster address "
        "(default $STREP_RAY_ADDRESS or local)",
    )
    bench.add_argument("--ray-cpus", type=int, default=1, help="with --executor ray: CPUs (and torch threads) per run")
    bench.set_defaults(fn=cmd_bench)

    rep = sub.add_parser(
        "reproduce",
        help="test each claim of the STREP paper with seeded benchmark runs and write a report with verdicts",
    )
    rep.add_argument(
        "--quick", action="store_true", help="about a minute (CI): short sequences, few iterations, two seeds"
    )
    rep.add_argument(
        "--out",
        "-o",
        default="runs/reproduce",
        help="cache of finished runs and trained models, per mode (default runs/reproduce); reruns resume from it",
    )
    rep.add_argument(
        "--docs",
        type=Path,
        help="the markdown report; figures and JSON go to a folder of the same stem beside it "
        "(default docs/reproduction.md; with --quick OUT/quick/reproduction.md)",
    )
    rep.add_argument("--data", type=Path, help="folder of the shared real data (default ../shared/data)")
    rep.add_argument("--fresh", action="store_true", help="ignore cached runs and run everything again")
    rep.add_argument("--no-progress", action="store_true", help="no progress bar")
    rep.set_defaults(fn=cmd_reproduce)

    serve = sub.add_parser("serve", help="start the web service (REST API, live events, web page)")
    serve.add_argument("--host", help="bind address (default 127.0.0.1; others need STREP_API_TOKEN)")
    serve.add_argument("--port", type=int, help="HTTP port (default 8000)")
    serve.add_argument("--data-dir", type=Path, help="jobs, uploads and results (default ./strep-data)")
    serve.add_argument(
        "--viewer-port",
        type=int,
        help="port of the 3D viewer (default 8080, or STREP_VIEWER_PORT; the next free one when taken; 0: any)",
    )
    serve.set_defaults(fn=cmd_serve)
    return parser


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("strep-studio")
    except PackageNotFoundError:  # pragma: no cover - run from a checkout that was never installed
        return "unknown"


def main(argv: Seq[str] | None = None) -> int:
    parser = make_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # the command's own usage, not the top level's
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        sub.choices[args.command].error(f"unrecognized arguments: {' '.join(extra)}")
    try:
        return int(args.fn(args) or 0)
    except StrepError as exc:
        print(f"strep: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("strep: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as exc:
        print(f"strep: error: {exc.strerror or exc}: {exc.filename or ''}".rstrip(": "), file=sys.stderr)
        return EXIT_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
