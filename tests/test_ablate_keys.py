"""The ablation's cache keys derive from the stage calls' own arguments (morphgs.ablation.jobs), so
none can go stale: every parameter of every stage's make() is keyed or explicitly ignored, an
argument cannot be passed without reaching the key, a value with no defined key is refused, and
bumping a stage's VERSION changes the keys of that stage and of what reads it, nothing else. (The
run-level half, a bumped version remaking exactly those outputs, is in test_ablate_e2e.py.)"""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest

from morphgs.ablation import build_plan, load_study
from morphgs.ablation.jobs import File, Job, Keyed, Out, fingerprint, job, keyed_parameters
from morphgs.ablation.stages import STAGES, stage_module

# a study with every stage: a plain condition, a calibrated one, the targets
STUDY = 'preset = "smoke"\n[conditions]\ntrain = ["morphological", "calibrated:morphological"]\n'
# what a stage may leave out of its key: thread counts only (they never change the bytes)
MAY_IGNORE = {"threads"}


def _plan(tmp_path: Path, text: str = STUDY) -> list[Job]:
    f = tmp_path / "study.toml"
    f.write_text(text, encoding="utf-8")
    return build_plan(load_study(f), tmp_path / "s")


def _downstream(jobs: list[Job], stage: str) -> set[str]:
    """Names of the jobs of `stage` and of every job that reads them, transitively."""
    hit = {j.ref.key for j in jobs if j.ref.stage == stage}
    for j in jobs:  # upstream first
        if any(u.ref.key in hit for u in j.depends_on()):
            hit.add(j.ref.key)
    return {f"{j.ref.stage}/{j.ref.name}" for j in jobs if j.ref.key in hit}


@pytest.mark.parametrize("stage", STAGES)
def test_every_parameter_of_every_stage_is_keyed_or_ignored(stage: str, tmp_path: Path) -> None:
    mod = stage_module(stage)
    assert isinstance(mod.VERSION, int) and isinstance(mod.RESUMABLE, bool)
    params = list(inspect.signature(mod.make).parameters)
    assert params[0] == "work"
    keyed, ignored = keyed_parameters(stage)
    assert sorted(keyed + ignored) == sorted(params[1:]) and set(ignored) <= MAY_IGNORE
    for p in params[1:]:  # keyword-only, no defaults: a caller cannot leave one out and get a default unkeyed
        assert mod.make.__code__.co_kwonlyargcount == len(params) - 1
        assert inspect.signature(mod.make).parameters[p].default is inspect.Parameter.empty, p
    if stage == "cleanfits":  # only captures given as photos have a clean fit
        from fit_helpers import make_dataset

        for i in range(3):
            make_dataset(tmp_path / f"cap{i}", views=12, size=(48, 48), gaussians=500, seed=i)
        text = STUDY + '[scenes]\ninputs = ["cap0", "cap1", "cap2"]\n'
        jobs = [j for j in _plan(tmp_path, text) if j.ref.stage == stage]
    else:
        jobs = [j for j in _plan(tmp_path) if j.ref.stage == stage]
    assert jobs, f"the study plans no {stage} job"
    for j in jobs:
        assert sorted(j.inputs) == sorted(keyed), j.ref.name  # exactly the keyed arguments are in the key
        assert sorted(j.kwargs) == sorted(keyed + ignored)


def test_an_argument_cannot_skip_the_key_and_an_unkeyable_value_is_refused(tmp_path: Path) -> None:
    kw = dict(testset_dir="t", row="input", run_dir=None, window=4, threads=1)
    a = job(tmp_path, "refine", "r", **kw)
    assert job(tmp_path, "refine", "r", **{**kw, "threads": 2}).ref == a.ref  # ignored: same key
    assert job(tmp_path, "refine", "r", **{**kw, "window": 5}).ref.key != a.ref.key
    with pytest.raises(TypeError, match=r"missing argument\(s\) \['window'\]"):
        job(tmp_path, "refine", "r", **{k: v for k, v in kw.items() if k != "window"})
    with pytest.raises(TypeError, match=r"unknown argument\(s\) \['colour'\]"):
        job(tmp_path, "refine", "r", **kw, colour=True)
    with pytest.raises(TypeError, match="no key is defined for a PosixPath"):
        job(tmp_path, "refine", "r", **{**kw, "testset_dir": tmp_path})
    with pytest.raises(TypeError, match="no key is defined for a object"):
        fingerprint({"a": [object()]})
    # an upstream output by its key, a file by its contents, a Keyed value by its fingerprint
    f = tmp_path / "model.toml"
    f.write_text("a = 1\n")
    one = fingerprint(File(str(f)))
    f.write_text("a = 2\n")
    assert fingerprint(File(str(f))) != one and fingerprint(File("")) == {"file_sha256": None}
    assert fingerprint(Out(a, "run")) == {"out": a.ref.key, "sub": "run"}
    assert fingerprint(Keyed(object(), {"id": 3})) == {"id": 3}


def test_levels_follow_the_inputs(tmp_path: Path) -> None:
    jobs = _plan(tmp_path)
    for j in jobs:
        ups = j.depends_on()
        assert j.level == (1 + max(u.level for u in ups) if ups else 0)
        assert all(jobs.index(u) < jobs.index(j) for u in ups)  # upstream first
    by = {f"{j.ref.stage}/{j.ref.name}": j.level for j in jobs}
    # a target's fits are one job per training scene, read by its training set
    assert by["captures/sample-0"] == 0 and by["pairfits/target-S8-sample-0"] == 1 and by["trainsets/target-S8"] == 2
    assert by["calibration/calibrated_morphological-S8"] == 3 and by["trainsets/calibrated_morphological-S8"] == 4
    assert by["trainsets/morphological"] == 1  # a perturbation's training set fits nothing
    assert by["report/report"] == max(by.values())


@pytest.mark.parametrize("stage", STAGES)
def test_bumping_a_stage_version_rekeys_it_and_what_reads_it_nothing_else(
        stage: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    before = _plan(tmp_path)
    monkeypatch.setattr(stage_module(stage), "VERSION", stage_module(stage).VERSION + 1)
    after = _plan(tmp_path)
    assert [f"{j.ref.stage}/{j.ref.name}" for j in after] == [f"{j.ref.stage}/{j.ref.name}" for j in before]
    changed = {f"{a.ref.stage}/{a.ref.name}" for a, b in zip(after, before) if a.ref.key != b.ref.key}
    assert changed == _downstream(before, stage)
    assert len(changed) < len(before) or stage == "captures"


def test_a_model_config_file_is_keyed_by_its_contents(tmp_path: Path) -> None:
    cfg = tmp_path / "tiny.toml"
    cfg.write_text("[model]\nwidth = 8\n", encoding="utf-8")
    text = f'preset = "smoke"\n[model]\nconfig = "{cfg}"\n'
    runs = {j.ref.name: j.ref.key for j in _plan(tmp_path, text) if j.ref.stage == "training"}
    cfg.write_text("[model]\nwidth = 16\n", encoding="utf-8")
    again = {j.ref.name: j.ref.key for j in _plan(tmp_path, text) if j.ref.stage == "training"}
    assert runs.keys() == again.keys() and all(runs[k] != again[k] for k in runs)


def test_a_new_kernel_version_of_an_op_rekeys_only_the_training_sets_that_use_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An op whose bytes changed (shatter, now in Rust) carries its implementation's version in
    the key of the training sets that use it: a cached study rebuilds those and what reads them,
    never the morphological set beside them."""
    from morphgs.ablation.stages import trainsets

    text = 'preset = "smoke"\n[conditions]\ntrain = ["morphological", "shatter~2"]\n'
    before = _plan(tmp_path, text)
    monkeypatch.setitem(trainsets.KERNELS, "shatter", trainsets.KERNELS["shatter"] + 1)
    after = _plan(tmp_path, text)
    changed = {f"{a.ref.stage}/{a.ref.name}" for a, b in zip(after, before) if a.ref.key != b.ref.key}
    sets = {n for n in changed if n.startswith("trainsets/")}
    assert sets and all("shatter" in n for n in sets), changed
    assert not any(n.startswith("trainsets/") and "morphological" in n for n in changed)
    assert any(n.startswith("training/") for n in changed)  # and what reads them
