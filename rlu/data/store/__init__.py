"""The native episode store: memory-mapped columnar files plus a JSON manifest.

``schema`` says what a dataset holds (the layout and the manifest's schema), ``writer`` writes one
atomically, ``reader`` opens one after checking every field and file. The names below are the
store's public API (``from rlu.data.store import DatasetWriter, open_dataset``).
"""

from rlu.data.store.reader import (
    Dataset,
    ZlibColumn,
    file_sha256,
    open_dataset,
    read_manifest,
    verify_checksums,
)
from rlu.data.store.schema import (
    ATTACHMENT_DIRS,
    DTYPES,
    ENCODINGS,
    FLAG_COLUMNS,
    FORMAT,
    FORMAT_VERSION,
    MANIFEST,
    Schema,
    is_attachment,
    partial_dir,
    segment_columns,
)
from rlu.data.store.writer import DatasetWriter, Deflated, SegmentColumns

__all__ = [
    "ATTACHMENT_DIRS",
    "DTYPES",
    "ENCODINGS",
    "FLAG_COLUMNS",
    "FORMAT",
    "FORMAT_VERSION",
    "MANIFEST",
    "Dataset",
    "DatasetWriter",
    "Deflated",
    "SegmentColumns",
    "Schema",
    "ZlibColumn",
    "file_sha256",
    "is_attachment",
    "open_dataset",
    "partial_dir",
    "read_manifest",
    "segment_columns",
    "verify_checksums",
]
