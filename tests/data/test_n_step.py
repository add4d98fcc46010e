"""The one n-step and frame-stack maths (rlu.data.views), on hand-computed numbers: the store's
views and the online replay of rlu.generate both build their transitions with it."""

from __future__ import annotations

import numpy as np

from rlu.data.views import n_step_counts, n_step_targets, stack_frames


def _targets(reward, discount, t, last, n, gamma, clip=None):
    return n_step_targets(
        np.asarray(reward, np.float32),
        np.asarray(discount, np.float32),
        np.asarray(t),
        np.asarray(last),
        n,
        gamma,
        clip,
    )


def test_n_step_return_discounts_and_stops_at_a_terminal():
    reward, discount, nxt = _targets([1, 2, 3, 0], [1, 1, 1, 0], [0], [3], 3, 0.5)
    np.testing.assert_array_equal(reward, [1 + 0.5 * 2 + 0.25 * 3])  # 2.75
    np.testing.assert_array_equal(discount, [1.0])
    np.testing.assert_array_equal(nxt, [3])
    reward, discount, _ = _targets([1, 2, 3, 0], [1, 0, 1, 0], [0], [3], 3, 0.5)
    np.testing.assert_array_equal(reward, [2.0])  # the reward after the terminal does not count
    np.testing.assert_array_equal(discount, [0.0])


def test_steps_past_the_segments_end_count_as_zero():
    # a terminal segment of 4 transitions (5 steps); windows of 3 from t = 2 and 3 run past it
    r, d = [1, 2, 3, 4, 0], [1, 1, 1, 0, 0]
    reward, discount, nxt = _targets(r, d, [2, 3], [4, 4], 3, 0.5)
    np.testing.assert_array_equal(reward, [3 + 0.5 * 4, 4])
    np.testing.assert_array_equal(discount, [0, 0])
    np.testing.assert_array_equal(nxt, [4, 4])


def test_one_step_transitions_clip_rewards_per_step():
    reward, discount, nxt = _targets(
        [-3, 0.5, 2, 0], [1, 1, 0, 0], [0, 1, 2], [3, 3, 3], 1, 0.99, clip=1.0
    )
    np.testing.assert_array_equal(reward, [-1, 0.5, 1])
    np.testing.assert_array_equal(discount, [1, 1, 0])
    np.testing.assert_array_equal(nxt, [1, 2, 3])
    # n > 1: clipped per step, then summed
    reward, _, _ = _targets([-3, 2, 0], [1, 1, 0], [0], [2], 2, 0.5, clip=1.0)
    np.testing.assert_array_equal(reward, [-1 + 0.5 * 1])


def test_n_step_counts_leave_out_windows_that_cross_a_truncation():
    length, terminal = np.array([5, 5, 2, 1]), np.array([True, False, False, False])
    np.testing.assert_array_equal(n_step_counts(length, terminal, 3), [4, 2, 0, 0])
    np.testing.assert_array_equal(n_step_counts(length, terminal, 1), [4, 4, 1, 0])


def test_the_stores_n_step_view_is_the_sum_written_out(tmp_path):
    from rlu.data import DatasetWriter, Schema, make_episode, open_dataset
    from rlu.data.views import TransitionView
    from rlu.types import ArraySpec, BoundedSpec

    schema = Schema({"x": ArraySpec((1,), "float32")}, BoundedSpec((1,), "float32"))
    rewards = np.array([1.0, 2.0, 3.0, 4.0, 5.0], np.float32)
    obs = {"x": np.arange(6, dtype=np.float32)[:, None]}
    with DatasetWriter(tmp_path / "d", schema) as w:
        w.append(make_episode(obs, np.zeros((5, 1), np.float32), rewards, terminal=True))
    view = TransitionView(open_dataset(tmp_path / "d"), n_step=3, gamma=0.9)
    batch = view.batch(np.arange(len(view)))
    starts = batch.observation["x"][:, 0].astype(int)
    np.testing.assert_array_equal(starts, [0, 1, 2, 3, 4])  # terminal: every transition
    for i, s in enumerate(starts):
        want, alive = 0.0, 1.0
        for k in range(3):  # the discount is 1 up to the terminal transition (step 4), then 0
            if s + k <= 4:
                want += 0.9**k * alive * rewards[s + k]
                alive *= 0.0 if s + k == 4 else 1.0
        assert abs(float(batch.reward[i]) - want) < 1e-5, (s, batch.reward[i], want)
        assert batch.discount[i] == (1.0 if s + 3 <= 4 else 0.0)


def test_stack_frames_puts_the_newest_frame_last():
    frames = np.arange(6 * 2 * 2, dtype=np.uint8).reshape(6, 2, 2)
    got = stack_frames(frames, np.array([0, 2]), 3)
    assert got.shape == (2, 2, 2, 3)
    for row, first in enumerate([0, 2]):
        for i in range(3):
            np.testing.assert_array_equal(got[row, :, :, i], frames[first + i])
