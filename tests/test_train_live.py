"""LivePairs: pairs rendered in DataLoader workers, seeded by (run seed, epoch, index), disjoint
across workers and ranks, resumable, and safe to fork after the parent rendered."""

from __future__ import annotations

import torch

import morphgs
from morphgs.data import LivePairs


def _live(**kw: object) -> LivePairs:
    opts: dict[str, object] = dict(frames=2, size=(24, 32), samples_per_epoch=6, seed=5, builtin_gaussians=2000,
                                   threads=1)
    opts.update(kw)
    return LivePairs(**opts)  # type: ignore[arg-type]


def test_a_sample_is_a_pure_function_of_seed_epoch_and_index() -> None:
    a, b = _live(), _live()
    s1, s2 = a.render_sample(0, 3), b.render_sample(0, 3)
    assert torch.equal(s1["corrupted"], s2["corrupted"]) and torch.equal(s1["clean"], s2["clean"])
    assert s1["corrupted"].shape == (3, 2, 24, 32)
    assert not torch.equal(s1["clean"], s1["corrupted"])  # a real corruption
    other = [a.render_sample(0, 4), a.render_sample(1, 3), _live(seed=6).render_sample(0, 3)]
    for o in other:
        assert o["seed"] != s1["seed"] and not torch.equal(o["corrupted"], s1["corrupted"])


def test_workers_render_disjoint_samples_after_the_parent_rendered() -> None:
    # the parent renders first (its native thread pool exists), then DataLoader forks two workers
    scene = morphgs.synthetic.scene(n_gaussians=1000, seed=0)
    morphgs.render(scene, morphgs.trajectory.for_scene(scene, 1, resolution=(32, 24))[0])
    ds = _live()
    serial = {(d["epoch"], d["index"]): d for d in ds}
    loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2, timeout=120)
    forked = list(loader)
    keys = [(int(d["epoch"]), int(d["index"])) for d in forked]
    assert sorted(keys) == sorted(serial) == [(0, i) for i in range(6)]  # each sample exactly once
    for d in forked:
        assert torch.equal(d["corrupted"], serial[(int(d["epoch"]), int(d["index"]))]["corrupted"])


def test_ranks_split_an_epoch_and_epochs_differ() -> None:
    r0 = [d["index"] for d in _live(rank=0, world_size=2)]
    r1 = [d["index"] for d in _live(rank=1, world_size=2)]
    assert r0 == [0, 2, 4] and r1 == [1, 3, 5]
    ds = _live()
    ds.set_epoch(1)
    assert [d["epoch"] for d in ds] == [1] * 6


def test_the_training_stream_resumes_at_a_batch_with_any_worker_count() -> None:
    ds = _live(samples_per_epoch=4)
    full = iter(ds.stream(start_batch=0, batch_size=2, rank=0, world_size=1))
    seq = [(d["epoch"], d["index"]) for d in (next(full) for _ in range(10))]
    assert seq[:4] == [(0, 0), (0, 1), (0, 2), (0, 3)] and seq[4:6] == [(1, 0), (1, 1)]  # endless over epochs
    resumed = ds.stream(start_batch=2, batch_size=2, rank=0, world_size=1)
    loader = torch.utils.data.DataLoader(resumed, batch_size=2, num_workers=2, timeout=120)
    it = iter(loader)
    got = []
    for _ in range(3):
        b = next(it)
        got += list(zip(b["epoch"].tolist(), b["index"].tolist()))
    assert got == seq[4:10]
