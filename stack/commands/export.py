"""`formation export`: a checkpoint -> verified policy files (+ one golden file).

    formation export CKPT --out policy                  # policy.pt, .pt2, .onnx, .npz + policy.golden.npz
    formation export CKPT --out policy --format onnx    # only policy.onnx (+ golden file)
    formation export --check policy.onnx                # re-verify a file against its golden file

Formats: torchscript (.pt), pt2 (torch.export), onnx (runs with numpy + onnxruntime only,
`deploy/robot.py`), npz (weights for one compiled kernel, numpy + numba only,
`deploy/npz_policy.py`: the fastest on the control path; typed actors without token mixers).
Each file is reloaded and compared with the eager actor for 1..21 robots before anything is
published. Exit code 0 when every file is verified, 1 when one is not (an
export then leaves no file), 2 for bad arguments.
"""

from __future__ import annotations

import sys
from pathlib import Path

from deploy.export import ExportError, check_export, export_checkpoint
from deploy.export.formats import FORMATS
from stack.commands import argtypes


def _formats(text: str) -> tuple[str, ...]:
    names = tuple(dict.fromkeys(part.strip() for part in text.split(",") if part.strip()))
    unknown = [n for n in names if n not in FORMATS]
    if unknown or not names:
        raise ValueError(f"--format: unknown format(s) {', '.join(unknown) or repr(text)}; "
                         f"choose from {', '.join(FORMATS)} (comma-separated)")
    return names


def _check_checkpoint(path: Path) -> None:
    """CheckpointError (a ValueError naming the fix) unless ``path`` is a MAPPO training
    checkpoint; the same message eval and bridge give, and exit 2 like theirs."""
    from controllers.mappo.checkpoint import checkpoint_config, load_checkpoint

    checkpoint_config(load_checkpoint(path))


def register(sub) -> None:
    p = sub.add_parser("export", description=__doc__)
    p.add_argument("checkpoint", type=Path, nargs="?", help="training checkpoint (checkpoint.pt)")
    p.add_argument("--out", type=argtypes.out_stem, default=None, metavar="STEM",
                   help="output stem: 'policy' (or 'policy.pt') writes policy.<suffix> per format, "
                        "and policy.golden.npz (required with CKPT)")
    p.add_argument("--format", default=None, metavar="LIST",
                   help=f"comma-separated formats from {', '.join(FORMATS)} (default: every one the "
                        "actor can take)")
    p.add_argument("--check", type=Path, default=None, metavar="POLICY",
                   help="re-verify an exported file (any format) against its golden file instead")
    p.set_defaults(func=run)


def run(args) -> int:
    try:
        if args.check is not None:
            if args.checkpoint is not None or args.out is not None:
                print("error: --check takes only the policy file", file=sys.stderr)
                return 2
            if not args.check.is_file():
                print(f"error: --check: no file {args.check}; give an exported policy "
                      "(policy.onnx, .pt, .pt2 or .npz)", file=sys.stderr)
                return 2
            report = check_export(args.check)
            print(f"OK {report.path} ({report.meta['file_format']}): golden file {report.golden.name} "
                  f"reproduced ({report.cases} comparisons, max abs diff {report.max_abs_diff:.3g})")
            return 0
        if args.checkpoint is None or args.out is None:
            print("error: give CKPT and --out policy (or --check policy.onnx)", file=sys.stderr)
            return 2
        if not args.checkpoint.is_file():
            print(f"error: CKPT: no file {args.checkpoint}; give a training checkpoint "
                  "(<run>/checkpoint.pt)", file=sys.stderr)
            return 2
        try:
            formats = None if args.format is None else _formats(args.format)
            _check_checkpoint(args.checkpoint)
        except ValueError as err:             # CheckpointError is one: a bad argument, nothing tried
            print(f"error: {err}", file=sys.stderr)
            return 2
        reports = export_checkpoint(args.checkpoint, args.out, formats)
    except (ExportError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    for report in reports:
        counts = report.meta["robot_counts"]
        span = f"{counts[0]}..{counts[-1]}" if len(counts) > 1 else str(counts[0])
        print(f"wrote {report.path} ({report.meta['file_format']}): verified against the eager actor "
              f"({report.cases} comparisons, max abs diff {report.max_abs_diff:.3g}, robots {span})")
    print(f"golden file: {reports[0].golden}")
    return 0
