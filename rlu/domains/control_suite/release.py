"""The control suite's release families: windows of 2 steps and whole episodes.

Records are ``dm_control_suite.py``'s sequences (:mod:`rlu.domains.records`). Windows keep their
values as stored (reward_t = reward[t], discount_t = discount[t]: the loader's r_t = reward[0],
p_t = discount[0]); is_first / is_last come from step_type (FIRST 0, LAST 2) and a LAST step with
discount 0 is terminal. ``*_episodes`` files are "RSA": reward_t = reward[t+1], discount_t =
discount[t+1], actions unshifted; terminal when the last discount is 0 (TFDS).
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
# A window of 2 steps is a few kB, an episode of 1000 steps of at most ~90 floats under 1
# MB; a task is at most 1.21 GiB in 100 shards.
FAMILIES = (
    Family(
        name="dm_control_suite",
        compression="gzip",
        parse=parse_sequences,
        segments=window_segments,
        encode=encode_sequence,
        whole_episodes=False,
        max_record_bytes=4 * _MiB,
        max_shard_bytes=256 * _MiB,
        record_note="a control-suite window of 2 steps is a few kB",
    ),
    Family(
        name="dm_control_suite_episodes",
        compression="gzip",
        parse=parse_sequences,
        segments=episode_segments,
        encode=encode_sequence,
        whole_episodes=True,
        max_record_bytes=16 * _MiB,
        max_shard_bytes=256 * _MiB,
        record_note="a control-suite episode of 1000 steps is under 1 MB",
    ),
)
