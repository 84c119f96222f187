"""Dataset generation: schema, determinism, resume without rewriting, sharding, atomic writes."""

import hashlib
import json

import h5py
import numpy as np
import pytest

from warpgnn import dataset
from warpgnn.fem_ref import generate as gen
from warpgnn.fem_ref.generate import SimulationSet, generate_set, parse_shard


def digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_set_follows_the_schema(tmp_path, tiny_preset):
    stats = generate_set(tmp_path, tiny_preset.sets[0], 0, tiny_preset, seed=3, device="cpu")
    assert stats["simulated"] == 3
    path = tmp_path / "A.h5"
    mesh = dataset.read_mesh(path)
    with h5py.File(path) as f:
        assert f.attrs["anatomy"] == "L1" and f.attrs["units"] == "SI"
        assert f.attrs["dt"] == pytest.approx(0.05)
        assert f.attrs["material_mu"] == pytest.approx(364.74)
        assert sorted(f["sims"]) == ["sim_0000", "sim_0001", "sim_0002"]
    for name in ("sim_0000", "sim_0001", "sim_0002"):
        sim = dataset.read_simulation(path, name)
        assert sim["q"].dtype == np.float32 and sim["q"].shape == (5, len(mesh.nodes), 3)
        k = sim["loaded"]
        assert 1 <= len(k) <= 3 and sim["u"].shape == (5, len(k), 3)
        mag = np.linalg.norm(sim["u"][-1], axis=1)
        assert ((mag >= 0.005 - 1e-7) & (mag <= 0.025 + 1e-7)).all()
        assert np.allclose(sim["q"][:, k] - mesh.nodes[k], sim["u"], atol=1e-6)
        assert np.abs(sim["q"][:, mesh.fixed] - mesh.nodes[mesh.fixed]).max() < 1e-7
        assert np.isfinite(sim["sigma"]).all() and np.abs(sim["sigma"][-1]).max() > 1.0
    assert not list(tmp_path.glob("*.tmp"))


def test_resume_skips_finished_simulations_and_never_rewrites(tmp_path, tiny_preset):
    spec = tiny_preset.sets[0]
    first = generate_set(tmp_path, SimulationSet(spec.name, spec.anatomy, 2), 0, tiny_preset, seed=1, device="cpu")
    before = dataset.read_simulation(tmp_path / "A.h5", "sim_0001")
    again = generate_set(tmp_path, SimulationSet(spec.name, spec.anatomy, 2), 0, tiny_preset, seed=1, device="cpu")
    assert first["simulated"] == 2 and again["simulated"] == 0 and again["skipped_existing"] == 2
    done = generate_set(tmp_path, spec, 0, tiny_preset, seed=1, device="cpu")  # complete the set
    assert done["simulated"] == 1 and done["skipped_existing"] == 2
    after = dataset.read_simulation(tmp_path / "A.h5", "sim_0001")
    assert all(np.array_equal(before[k], after[k]) for k in dataset.REQUIRED_SIM_FIELDS)
    # the same seed draws the same case for the same simulation in a fresh directory
    fresh = tmp_path / "fresh"
    generate_set(fresh, spec, 0, tiny_preset, seed=1, device="cpu")
    assert np.array_equal(dataset.read_simulation(fresh / "A.h5", "sim_0002")["u"],
                          dataset.read_simulation(tmp_path / "A.h5", "sim_0002")["u"])


def test_interrupted_write_leaves_the_file_untouched(tmp_path, tiny_preset, monkeypatch):
    spec = tiny_preset.sets[0]
    generate_set(tmp_path, SimulationSet(spec.name, spec.anatomy, 1), 0, tiny_preset, seed=0, device="cpu")
    before = digest(tmp_path / "A.h5")

    def crash(*_):
        raise KeyboardInterrupt

    monkeypatch.setattr(dataset, "write_simulation", crash)
    with pytest.raises(KeyboardInterrupt):
        generate_set(tmp_path, spec, 0, tiny_preset, seed=0, device="cpu")
    assert digest(tmp_path / "A.h5") == before
    assert not list(tmp_path.glob("*.tmp"))


def test_shards_split_the_sets(tmp_path, tiny_preset, monkeypatch):
    monkeypatch.setitem(gen.PRESETS, "tiny", lambda: tiny_preset)
    gen.generate(tmp_path, "tiny", device="cpu", shard="1/2")
    assert sorted(p.name for p in tmp_path.glob("*.h5")) == ["B.h5"]
    gen.generate(tmp_path, "tiny", device="cpu", shard="0/2")
    assert sorted(p.name for p in tmp_path.glob("*.h5")) == ["A.h5", "B.h5"]
    for sim in ("sim_0000", "sim_0001"):
        assert len(dataset.read_simulation(tmp_path / "B.h5", sim)["loaded"]) == 2
    assert (tmp_path / "manifest.0-of-2.json").exists() and (tmp_path / "manifest.1-of-2.json").exists()


def test_failed_simulations_are_redrawn(tmp_path, tiny_preset, monkeypatch):
    """A load case that inverts elements is reported and replaced by the next attempt."""
    real = gen.LoadSampler

    class FirstAttemptCrushes(real):
        def sample(self, rng, n_loads=None):
            case = super().sample(rng, n_loads)
            if not hasattr(self, "crushed"):
                self.crushed = True
                case.displacement = case.displacement * 40.0  # metres of compression: inverts
            return case

    monkeypatch.setattr(gen, "LoadSampler", FirstAttemptCrushes)
    messages = []
    stats = generate_set(tmp_path, tiny_preset.sets[0], 0, tiny_preset, seed=0, device="cpu", log=messages.append)
    assert stats["simulated"] == 3 and stats["resampled"] >= 1
    assert any("element" in m and "resampled" in m for m in messages)
    sim = dataset.read_simulation(tmp_path / "A.h5", "sim_0000")
    assert np.isfinite(sim["q"]).all()


def test_parse_shard():
    assert parse_shard(None) == (0, 1) and parse_shard("2/4") == (2, 4)
    for bad in ("4/4", "x/2", "1"):
        with pytest.raises(ValueError):
            parse_shard(bad)


def test_smoke_preset_has_every_file_train_and_eval_read():
    """`warpgnn train --data DIR` reads L1..L4 and validates on every fifth simulation of L5."""
    from warpgnn.data import TEST_FILE, TRAIN_FILES, VALIDATION_EVERY

    counts = {s.name: s.count for s in gen.PRESETS["smoke"]().sets}
    assert all(counts.get(stem, 0) >= 1 for stem in (*TRAIN_FILES, TEST_FILE))
    assert len(range(counts[TEST_FILE])[::VALIDATION_EVERY]) >= 1


def test_paper_preset_is_the_papers():
    paper = gen.PRESETS["paper"]()
    assert [(s.name, s.anatomy, s.count, s.n_loads) for s in paper.sets] == [
        *[(f"L{i}", f"L{i}", 190, None) for i in range(1, 6)], ("extra", "L1", 33, None), ("extra_star", "L5", 10, 4)]
    assert (paper.solver.duration, paper.solver.snapshots, paper.solver.viscosity) == (1.0, 20, True)
    assert paper.displacement_range == (0.005, 0.025)


def test_wide_preset_spreads_the_paper_budget_over_forty_livers_and_keeps_the_papers_test_cases():
    wide, paper = gen.PRESETS["wide"](), gen.PRESETS["paper"]()
    train = [s for s in wide.sets if s.name.startswith("W")]
    assert len(train) == 40 and {s.count for s in train} == {24} and all(s.name == s.anatomy for s in train)
    assert 900 <= sum(s.count for s in train) <= 1000  # about the paper's 760 training simulations (+L5's 190)
    streams = [s.stream for s in wide.sets]
    assert len(set(streams)) == len(streams)
    # the unseen sets are the paper's own: same anatomy, count, tools and random stream (its place in paper)
    for s in wide.sets[40:]:
        k = next(k for k, p in enumerate(paper.sets) if p.name == s.name)
        assert (s.anatomy, s.count, s.n_loads, s.stream) == (paper.sets[k].anatomy, paper.sets[k].count,
                                                              paper.sets[k].n_loads, k)
    assert [s.name for s in wide.sets[40:]] == ["L5", "extra_star"]
    assert (wide.solver, wide.displacement_range) == (paper.solver, paper.displacement_range)


def test_a_sets_stream_decides_its_simulations(tmp_path, tiny_preset, monkeypatch):
    """generate() draws a set's cases from its stream, not its place: B moved first, given its old place as its
    stream, simulates exactly what it did second."""
    from dataclasses import replace

    monkeypatch.setitem(gen.PRESETS, "t1", lambda: tiny_preset)
    moved = replace(tiny_preset, sets=[replace(tiny_preset.sets[1], stream=1)])
    monkeypatch.setitem(gen.PRESETS, "t2", lambda: moved)
    gen.generate(tmp_path / "a", "t1", seed=5, device="cpu")
    gen.generate(tmp_path / "b", "t2", seed=5, device="cpu")
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert manifest["train_sets"] == ["L1", "L2", "L3", "L4"]  # what `warpgnn train` will read (data.py)
    for name in dataset.simulation_names(tmp_path / "a" / "B.h5"):
        a, b = (dataset.read_simulation(tmp_path / d / "B.h5", name) for d in "ab")
        assert np.array_equal(a["q"], b["q"]) and np.array_equal(a["loaded"], b["loaded"])


def test_real_preset_tests_three_real_livers_and_trains_on_none():
    real = gen.PRESETS["real"]()
    assert [(s.name, s.anatomy, s.count) for s in real.sets] == [
        ("real_vhf", "real_vhf", 190), ("real_vhm", "real_vhm", 190), ("real_sofa", "real_sofa", 190)]
    assert real.train_sets == () and len({s.stream for s in real.sets}) == 3


def test_a_test_only_preset_keeps_the_folders_training_files(tmp_path, tiny_preset, monkeypatch):
    """`generate --preset real` into a folder of another preset leaves the manifest's training files as they were
    (train reads them there), where a preset with training files of its own sets them."""
    from dataclasses import replace

    wide_like = replace(tiny_preset, sets=tiny_preset.sets[:1], train_sets=("A*",))
    test_only = replace(tiny_preset, sets=[replace(tiny_preset.sets[1], count=1)], train_sets=())
    monkeypatch.setitem(gen.PRESETS, "w", lambda: wide_like)
    monkeypatch.setitem(gen.PRESETS, "r", lambda: test_only)
    gen.generate(tmp_path, "w", seed=1, device="cpu")
    gen.generate(tmp_path, "r", seed=1, device="cpu")
    assert json.loads((tmp_path / "manifest.json").read_text())["train_sets"] == ["A*"]
