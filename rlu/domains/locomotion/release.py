"""Locomotion's release families: windows of 2 or 40 steps and whole episodes, with the camera.

The control suite's record layout (:mod:`rlu.domains.records`), with the walker's 64x64x3
egocentric camera stored raw (``CAMERA_KEY``); the same alignment rules.
"""

from __future__ import annotations

from rlu.domains.records import (
    Family,
    encode_sequence,
    episode_segments,
    parse_sequences,
    window_segments,
)

_MiB, _GiB = 1 << 20, 1 << 30


# Limits: well above what the release holds (sizes from the TFDS catalog, which describe the same
# data re-encoded; docs/release_format.md §5), well below what a machine cannot hold.
# A seq40 window with its 64x64x3 camera is 0.5 MB; an episode keeps 12,288 camera bytes per
# step (about 12-18 MB); a task is 23.1 GiB in 100 shards.
FAMILIES = (
    Family(
        name="dm_locomotion",
        compression="gzip",
        parse=parse_sequences,
        segments=window_segments,
        encode=encode_sequence,
        whole_episodes=False,
        max_record_bytes=16 * _MiB,
        max_shard_bytes=4 * _GiB,
        record_note="a locomotion window of 2 or 40 steps is under 1 MB",
    ),
    Family(
        name="dm_locomotion_episodes",
        compression="gzip",
        parse=parse_sequences,
        segments=episode_segments,
        encode=encode_sequence,
        whole_episodes=True,
        max_record_bytes=128 * _MiB,
        max_shard_bytes=4 * _GiB,
        record_note="a locomotion episode with its camera is about 12-18 MB",
    ),
)
