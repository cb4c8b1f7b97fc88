"""moex.jobs: a run's seeds are its own (run r is the same network in a batch of any size), jobs
share a batch only where everything that shapes a training step agrees, and phase 1's cache is
keyed by what phase 1 depends on alone. (`train_jobs` itself: tests/test_packing.py.)"""

import dataclasses

import torch

from moex.config import Config
from moex.jobs import initial_parameters, packing_key, phase1_cache, run_generators, run_seeds
from moex.tasks import task_config


def test_run_r_draws_the_same_in_a_batch_of_any_size():
    assert run_seeds(5, 3) == run_seeds(5, 7)[:3] and run_seeds(5, 3) != run_seeds(6, 3)
    assert len(set(run_seeds(5, 50))) == 50
    one, many = run_generators(5, 1)[0], run_generators(5, 4)[0]
    assert torch.equal(torch.rand(8, generator=one), torch.rand(8, generator=many))
    plain, salted = run_generators(5, 1)[0], run_generators(5, 1, salt=0xE7A1)[0]
    assert not torch.equal(torch.rand(8, generator=plain), torch.rand(8, generator=salted))
    cfg = Config(num_runs=3)
    experts, gating = initial_parameters(cfg, 2, 2, torch.float64)
    experts1, gating1 = initial_parameters(dataclasses.replace(cfg, num_runs=1), 2, 2,
                                           torch.float64)
    assert all(torch.equal(experts[k][:1], experts1[k]) for k in experts)
    assert all(torch.equal(gating[k][:1], gating1[k]) for k in gating)
    assert initial_parameters(Config(task=task_config("reber")), 2, 0, torch.float64)[0] == {}


def test_jobs_share_a_batch_where_every_training_setting_agrees():
    cfg = Config()
    assert packing_key(cfg) == packing_key(dataclasses.replace(cfg, seed=4, num_runs=9))
    assert packing_key(cfg) == packing_key(dataclasses.replace(
        cfg, task=task_config("lissajous2", switch_prob=0.25)))  # other data, same steps
    model = dataclasses.replace(cfg.model, num_experts=3)
    assert packing_key(cfg) != packing_key(dataclasses.replace(cfg, model=model))
    assert packing_key(cfg) != packing_key(dataclasses.replace(cfg, precision="float32"))
    tracking = dataclasses.replace(cfg, eval=dataclasses.replace(cfg.eval, every=100))
    assert packing_key(cfg) != packing_key(tracking)  # trains alone


def test_phase_1_is_cached_by_what_phase_1_depends_on(tmp_path):
    cfg = Config(cache_dir=str(tmp_path))
    assert phase1_cache(Config()) is None
    path = phase1_cache(cfg)
    assert path.parent == tmp_path and path.name.startswith("phase1-")
    gating = dataclasses.replace(cfg.model, gating=dataclasses.replace(cfg.model.gating,
                                                                       context_size=30))
    assert phase1_cache(dataclasses.replace(cfg, model=gating)) == path
    assert phase1_cache(dataclasses.replace(cfg, seed=1)) != path
    assert phase1_cache(dataclasses.replace(cfg, task=task_config("lissajous2",
                                                                  switch_prob=0.25))) != path
