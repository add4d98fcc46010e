"""``rlu validate``, ``rlu export`` and ``rlu import``."""

from __future__ import annotations

import argparse

_DATASET_HELP = (
    "the dataset: a folder, or a name as rlu.load_dataset takes it (a task id: the bundled or "
    "converted release data; a TFDS name)"
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("validate", help="check a stored dataset; exit code 1 on any problem")
    p.add_argument("path", help=_DATASET_HELP)
    p.add_argument("--no-checksums", action="store_true", help="skip the sha256 of every file")
    p.set_defaults(func=_validate)

    from rlu.data.formats import FORMATS

    def targets(attr: str) -> str:
        return "; ".join(
            f"{f.name}: {getattr(f, attr)}" for f in FORMATS.values() if getattr(f, attr)
        )

    p = sub.add_parser("export", help="export a stored dataset to another format")
    p.add_argument("path", help=_DATASET_HELP)
    p.add_argument("--format", required=True, choices=list(FORMATS))
    p.add_argument("-o", "--out", help=f"output file ({targets('target')})")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing -o file, if rlu wrote it (a file another tool wrote is never "
        "replaced)",
    )
    _format_options(p, "export")
    p.set_defaults(func=_export)

    p = sub.add_parser("import", help="import a dataset of another format into the store")
    p.add_argument("src", help=targets("source"))
    p.add_argument("--format", required=True, choices=list(FORMATS))
    needs = ", ".join(f.name for f in FORMATS.values() if f.task_required)
    p.add_argument(
        "--task",
        help=f"task id, e.g. control_suite/cartpole_swingup ({needs}: required unless the file "
        "is an export of rlu's; others: default, the schema of the dataset's spaces)",
    )
    p.add_argument("--out", required=True, help="new dataset directory")
    _format_options(p, "import")
    p.set_defaults(func=_import)


def _format_options(p: argparse.ArgumentParser, command: str) -> None:
    """The options the registered formats add to ``command`` (one flag for formats sharing it)."""
    from rlu.data.formats import FORMATS

    seen: dict[str, list[str]] = {}
    helps: dict[str, str] = {}
    for f in FORMATS.values():
        for o in f.options:
            if command in o.commands:
                seen.setdefault(o.flag, []).append(f.name)
                helps[o.flag] = o.help
    for flag, names in seen.items():
        p.add_argument(flag, help=f"{', '.join(names)}: {helps[flag]}")


def _validate(args: argparse.Namespace) -> int:
    import os

    from rlu.data import load_dataset
    from rlu.data.validate import validate

    # a folder is validated as it is (problems reported, not raised); a name is resolved first
    path = args.path if os.path.exists(args.path) else str(load_dataset(args.path).path)
    report = validate(path, checksums=not args.no_checksums)
    for c in report.checked:
        print(f"ok   {c}")
    for n in report.notes:
        print(f"note {n}")
    for p in report.problems:
        print(f"FAIL {p}")
    print(f"{args.path}: {'valid' if report.ok else f'{len(report.problems)} problem(s)'}")
    return 0 if report.ok else 1


def _note(line: str) -> None:
    print(f"note: {line}")


def _export(args: argparse.Namespace) -> int:
    from rlu.data import load_dataset
    from rlu.data.formats import export_dataset, options_of

    options = options_of(args.format, "export", vars(args))
    ds = load_dataset(args.path)
    out = export_dataset(args.format, ds, args.out, args.overwrite, _note, **options)
    print(f"wrote {out}")
    return 0


def _import(args: argparse.Namespace) -> int:
    from pathlib import Path

    from rlu.data.formats import import_dataset, options_of
    from rlu.data.store import open_dataset
    from rlu.files import check_output

    options = options_of(args.format, "import", vars(args))
    inputs = [args.src] if Path(args.src).exists() else []
    inputs += [v for v in options.values() if v is not None and Path(v).exists()]
    check_output(args.out, inputs, what="dataset folder")
    dest = import_dataset(args.format, args.src, args.out, args.task, **options)
    ds = open_dataset(dest)
    print(f"wrote {dest}: {len(ds)} episodes, {ds.num_steps} steps")
    return 0
