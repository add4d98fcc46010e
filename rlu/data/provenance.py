"""Where a dataset's steps came from, in the few fields a reported number carries.

A score beside the paper's must say what data produced it (the paper's agents learned from the
release's files). :func:`data_source` reads a manifest's provenance, as each writer of rlu records
it (``rlu convert``, ``rlu generate``, the imports, the synthetic writer), into::

    {"source": "release" | "generated" | "imported" | "synthetic" | "unknown",
     "family": ..., "files": ...,       # release: the family and how many of its files
     "scale": ..., "command": ...,      # generated: the recipe's scale and the command
     "format": ...}                     # imported: d4rl, d3rlpy or minari
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

IMPORT_FORMATS = ("d4rl", "d3rlpy", "minari")


def data_source(manifest: Mapping[str, Any]) -> dict[str, Any]:
    """The data-source summary of a dataset's manifest (see the module docstring)."""
    prov = manifest.get("provenance") or {}
    if not isinstance(prov, Mapping):
        return {"source": "unknown"}
    source = prov.get("source")
    if source == "rl_unplugged release":
        out: dict[str, Any] = {"source": "release", "family": str(prov.get("family"))}
        if isinstance(prov.get("files"), list):
            out["files"] = len(prov["files"])
        for key in ("run", "challenge"):
            if prov.get(key) is not None:
                out[key] = prov[key]
        return out
    if prov.get("generator") == "rlu generate":
        settings = prov.get("settings") if isinstance(prov.get("settings"), Mapping) else {}
        out = {"source": "generated", "command": str(prov.get("command", ""))}
        if settings.get("scale") is not None:
            out["scale"] = str(settings["scale"])
        return out
    if source in IMPORT_FORMATS:
        return {"source": "imported", "format": source}
    if source == "synthetic":
        return {"source": "synthetic"}
    return {"source": "unknown"}
