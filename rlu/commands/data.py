"""``rlu validate``, ``rlu export`` and ``rlu import``."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("validate", help="check a stored dataset; exit code 1 on any problem")
    p.add_argument("path")
    p.add_argument("--no-checksums", action="store_true", help="skip the sha256 of every file")
    p.set_defaults(func=_validate)

    p = sub.add_parser("export", help="export a stored dataset to another format")
    p.add_argument("path")
    p.add_argument("--format", required=True, choices=["d4rl"])
    p.add_argument("-o", "--out", required=True, help="output file (.npz for d4rl)")
    p.set_defaults(func=_export)

    p = sub.add_parser("import", help="import a dataset of another format into the store")
    p.add_argument("src", help="input file (.npz or .hdf5 for d4rl)")
    p.add_argument("--format", required=True, choices=["d4rl"])
    p.add_argument("--task", required=True, help="task id, e.g. control_suite/cartpole_swingup")
    p.add_argument("--out", required=True, help="new dataset directory")
    p.set_defaults(func=_import)


def _validate(args: argparse.Namespace) -> int:
    from rlu.data.validate import validate

    report = validate(args.path, checksums=not args.no_checksums)
    for c in report.checked:
        print(f"ok   {c}")
    for p in report.problems:
        print(f"FAIL {p}")
    print(f"{args.path}: {'valid' if report.ok else f'{len(report.problems)} problem(s)'}")
    return 0 if report.ok else 1


def _export(args: argparse.Namespace) -> int:
    from rlu.data.d4rl import export_d4rl
    from rlu.data.store import open_dataset

    out = export_d4rl(open_dataset(args.path), args.out)
    print(f"wrote {out}")
    return 0


def _import(args: argparse.Namespace) -> int:
    from rlu.data.d4rl import import_d4rl
    from rlu.data.store import open_dataset

    dest = import_d4rl(args.src, args.out, args.task)
    ds = open_dataset(dest)
    print(f"wrote {dest}: {len(ds)} episodes, {ds.num_steps} steps")
    return 0
