"""``robtraj import SRC -o REC.h5``: real data from other trackers (docs/import.md)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from .._errors import UserError
from ..recording import Recording, write_recording
from . import _output


def register(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "import",
        help="convert another tracker's file into a schema-1 recording",
        description=(
            "Convert real data from other trackers into a schema-1 recording (source=import): "
            "NDI Optotrak N3D marker files, 6-DOF pose CSV (laser tracker with a 6-DOF probe; "
            "a folder imports every CSV in it) and NatNet packet captures. See docs/import.md."
        ),
    )
    p.add_argument("src", metavar="SRC", help="input file (or folder of pose CSV files)")
    p.add_argument(
        "-o",
        "--out",
        required=True,
        metavar="REC.h5",
        help="output file; for a folder SRC a folder, into which one .h5 per CSV series is "
        "written (a folder holding a single CSV may also be written to one .h5 file)",
    )
    p.add_argument(
        "--format",
        choices=["n3d", "pose-csv", "natnet"],
        help="input format (default: from the extension: .n3d, .csv, .bin)",
    )
    p.add_argument(
        "--preset",
        help="built-in settings: ipa-ur10 (pose-csv), optotrak-probe (n3d constellation)",
    )
    p.add_argument("--mapping", metavar="FILE", help="pose-csv: JSON column mapping")
    p.add_argument(
        "--rate",
        type=float,
        metavar="HZ",
        help="frame rate: n3d overrides the header; pose-csv spacing (default 1 Hz); "
        "natnet uses frame/HZ instead of timestamps",
    )
    p.add_argument(
        "--constellation",
        metavar="FILE",
        help="tool constellation: JSON or CSV file, or a built-in name (optotrak-probe)",
    )
    p.add_argument("--model-id", type=int, help="natnet: only the markers of this model")
    g = p.add_argument_group("pose-csv columns (override the preset or mapping)")
    g.add_argument("--position-cols", metavar="X,Y,Z", help="measured position columns")
    g.add_argument("--rotation-cols", metavar="RX,RY,RZ", help="measured Euler angle columns")
    g.add_argument("--position-unit", choices=["m", "mm"], help="measured position unit")
    g.add_argument("--angle-unit", choices=["rad", "deg"], help="measured angle unit")
    g.add_argument(
        "--euler", metavar="SEQ", help="Euler sequence: XYZ intrinsic, xyz extrinsic, ..."
    )
    g.add_argument("--delimiter", help="field separator (default ',')")
    g.add_argument("--decimal", help="decimal mark (default '.')")
    p.add_argument("--force", action="store_true", help="overwrite an existing output")
    p.set_defaults(func=run)
    return p


def _pose_mapping(args: argparse.Namespace) -> dict[str, Any] | None:
    """A mapping dict built from --mapping and the column flags (None: none given)."""
    from ..importers import load_mapping

    flags = {
        "position": args.position_cols,
        "rotation": args.rotation_cols,
        "position_unit": args.position_unit,
        "angle_unit": args.angle_unit,
        "euler": args.euler,
    }
    if (
        args.mapping is None
        and all(v is None for v in flags.values())
        and not (args.delimiter or args.decimal)
    ):
        return None
    base: dict[str, Any] = {}
    if args.preset or args.mapping:
        base = load_mapping(args.preset, args.mapping)
    measured = dict(base.get("measured", {}))
    for key, value in flags.items():
        if value is None:
            continue
        if key in ("position", "rotation"):
            value = [c.strip() for c in value.split(",")]
            if len(value) != 3:
                raise UserError(f"--{key}-cols needs 3 comma-separated column names")
        measured[key] = value
    if measured:
        base["measured"] = measured
    if args.delimiter:
        base["delimiter"] = args.delimiter
    if args.decimal:
        base["decimal"] = args.decimal
    return base


def run(args: argparse.Namespace) -> int:
    from .. import importers

    src, out = Path(args.src), Path(args.out)
    if not src.exists():
        raise UserError(f"{src}: no such file")
    if not src.is_dir():
        _output.check([out], force=args.force)
    if args.rate is not None and not args.rate > 0:
        raise UserError(f"--rate must be > 0 Hz, got {args.rate}")
    fmt = args.format or importers.guess_format(src)
    if fmt == "pose-csv":
        if args.constellation or args.model_id is not None:
            raise UserError("--constellation and --model-id do not apply to pose-csv")
        mapping = _pose_mapping(args)
        preset = None if mapping is not None else args.preset
        if src.is_dir():
            return _run_folder(src, out, preset, mapping, args)
        rec = importers.import_pose_csv(src, preset=preset, mapping=mapping, rate=args.rate)
    elif fmt == "n3d":
        if args.mapping or args.model_id is not None:
            raise UserError("--mapping and --model-id do not apply to n3d")
        rec = importers.import_file(
            src, "n3d", constellation=args.constellation, preset=args.preset, rate=args.rate
        )
    else:
        if args.mapping or args.preset or args.constellation:
            raise UserError("--mapping, --preset and --constellation do not apply to natnet")
        from acquisition.natnet import import_natnet

        rec = import_natnet(src, model_id=args.model_id, rate=args.rate)
    with _output.new_file(out) as tmp:
        write_recording(rec, tmp)
    _say(out, rec)
    return 0


# an -o with one of these suffixes names a file, anything else a folder
_FILE_SUFFIXES = (".h5", ".hdf5")


def _run_folder(
    src: Path, out: Path, preset: str | None, mapping: dict[str, Any] | None, args
) -> int:
    """A folder of pose CSV files: one .h5 per series into the folder `out`, or, where
    the folder holds a single series and `out` names a file, that file."""
    from ..importers import import_pose_folder

    as_file = out.suffix.lower() in _FILE_SUFFIXES or (out.exists() and not out.is_dir())
    n_series = sum(1 for _ in src.rglob("*.csv"))  # import_pose_folder imports each
    if as_file and n_series > 1:
        raise UserError(
            f"{src} holds {n_series} pose series (.csv files), written as one .h5 each into "
            f"a folder: name a folder with -o, not the file {out}"
        )
    if as_file:
        _output.check([out], force=args.force)
    else:
        _output.check(folders=[out], force=args.force)
    recs = import_pose_folder(src, preset=preset, mapping=mapping, rate=args.rate)
    if as_file:
        if len(recs) != 1:  # the folder changed since it was counted
            raise UserError(f"{src} holds {len(recs)} pose series: name a folder with -o")
        (rec,) = recs.values()
        with _output.new_file(out) as tmp:
            write_recording(rec, tmp)
        _say(out, rec)
        return 0
    names = {name: name.removesuffix(".csv").replace("/", "_") + ".h5" for name in recs}
    with _output.new_folder(out) as tmp:
        for name, rec in recs.items():
            write_recording(rec, tmp / names[name])
    for name, rec in recs.items():
        _say(out / names[name], rec)
    return 0


def _say(out: Path, rec: Recording) -> None:
    parts = [f"{rec.n_frames} frames", f"{rec.n_leds} LEDs"]
    if rec.robot is not None:
        parts.append(f"robot {rec.robot.model or 'dh'}")
    if rec.tool is not None:
        parts.append(f"tool of {rec.tool.led_ids.shape[0]} LEDs")
    print(f"wrote {out}: {', '.join(parts)}")
