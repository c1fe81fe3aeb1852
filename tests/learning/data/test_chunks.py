"""Chunk choice: one per trajectory, starting out of contact, about the target share with one."""

from __future__ import annotations

import numpy as np
import pytest

from diffcontact.learning.data.chunks import select_chunks
from diffcontact.learning.data.format import load_dataset

from .support import L


def test_select_chunks_hits_the_target_share_and_starts_out_of_contact():
    rng = np.random.default_rng(1)
    N, T = 2000, 30
    contact = rng.random((N, T)) < 0.15
    start, has = select_chunks(contact, L, 0.5, rng=3)
    assert start.dtype == np.int64 and has.dtype == bool
    assert ((start >= 0) & (start <= T - L)).all()
    assert not contact[np.arange(N), start].any()
    windows = np.stack([contact[n, s : s + L] for n, s in enumerate(start)])
    assert (windows.any(1) == has).all()
    assert has.sum() == N // 2
    again = select_chunks(contact, L, 0.5, rng=3)
    assert (again[0] == start).all()  # seeded
    _, has_03 = select_chunks(contact, L, 0.3, rng=3)
    assert has_03.sum() == round(0.3 * N)


def test_select_chunks_forced_kinds_and_unchunkable():
    contact = np.zeros((3, 10), dtype=bool)
    contact[0, 1:] = True  # only chunk: start 0, contains a contact
    contact[2, 4] = True  # both kinds possible
    start, has = select_chunks(contact, L, 0.0, rng=0)
    assert start[0] == 0 and has[0]  # forced even with contact_fraction 0
    assert not has[1] and not has[2]  # trajectory 1 has no contact at all
    _, has = select_chunks(contact, L, 1.0, rng=0)
    assert has.tolist() == [True, False, True]
    contact[1, :6] = True  # every possible start (0..5) in contact
    with pytest.raises(ValueError, match=r"1 of 3 trajectories \(1\).*states 0\.\.5"):
        select_chunks(contact, L, 0.5)
    with pytest.raises(ValueError, match="fewer than chunk_length"):
        select_chunks(np.zeros((2, 4), dtype=bool), L)


def test_contact_share_near_target(bp5_dir):
    ds = load_dataset(bp5_dir)
    for name in ("train", "val", "test"):
        split = ds.split(name)
        N = len(split)
        contact = split.contact.numpy()
        S = contact.shape[1] - L + 1
        windows = np.lib.stride_tricks.sliding_window_view(contact, L, axis=1).any(-1)
        ok = ~contact[:, :S]
        can_c, can_f = (ok & windows).any(1), (ok & ~windows).any(1)
        # the target round(N / 2), as far as the trajectories allow
        target = int(np.clip(round(0.5 * N + 1e-9), (can_c & ~can_f).sum(), can_c.sum()))
        assert int(split.chunk_has_contact.sum()) == target
        assert abs(target - 0.5 * N) <= 1, "BP5 should reach the target"
