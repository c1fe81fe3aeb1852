"""Helpers shared by the training tests: datasets written with numpy only."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import torch

import diffcontact as dc

SMALL = {"hidden": (16, 16), "progress": False}


def write_dataset(folder, config, n=(8, 4, 4), steps=15, chunk=5, seed=0, nan_train=()):
    """A dataset folder in the format of docs/conventions.md, written with numpy only.

    From each trajectory one chunk whose first state is out of contact; every
    other trajectory takes a chunk with a contact when it has one.
    ``nan_train``: train chunks whose states 2.. are set to NaN.
    """
    folder.mkdir(parents=True, exist_ok=True)
    system = dc.load_system(config)
    files = {}
    for k, (split, count) in enumerate(zip(("train", "val", "test"), n, strict=True)):
        traj = system.simulate(system.sample_initial_conditions(count, seed=seed + k), steps)
        with torch.no_grad():
            contact = (system.gaps(traj[..., 0, :, :]) < 0).any(-1).numpy()
        rng = np.random.default_rng(seed + k)
        starts, has = [], []
        for i in range(count):
            ok = [s for s in range(steps + 2 - chunk) if not contact[i, s]]
            with_contact = [s for s in ok if contact[i, s : s + chunk].any()]
            s = int(rng.choice(with_contact if with_contact and i % 2 == 0 else ok))
            starts.append(s)
            has.append(bool(contact[i, s : s + chunk].any()))
        t = traj.numpy()
        chunks = np.stack([t[i, s : s + chunk] for i, s in enumerate(starts)])
        if split == "train":
            for i in nan_train:
                chunks[i, 2:] = np.nan
        path = folder / f"{split}.npz"
        np.savez(
            path,
            traj=t,
            chunks=chunks,
            chunk_start=np.array(starts, dtype=np.int64),
            chunk_has_contact=np.array(has),
            contact=contact,
        )
        files[path.name] = hashlib.sha256(path.read_bytes()).hexdigest()
    meta = {
        "format_version": 1,
        "config": system.config.model_dump(mode="json"),
        "task": system.name,
        "seed": seed,
        "seeds": {"train": seed, "val": seed + 1, "test": seed + 2},
        "dt": system.dt,
        "n_train": n[0],
        "n_val": n[1],
        "n_test": n[2],
        "n_states": steps + 1,
        "noise_std": 0.0,
        "chunk_length": chunk,
        "diffcontact_version": dc.__version__,
        "created": "test",
        "files": files,
        "arguments": {},
    }
    (folder / "metadata.json").write_text(json.dumps(meta))
    return folder
