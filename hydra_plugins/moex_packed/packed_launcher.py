"""`hydra/launcher=packed`: moex's launcher that trains a sweep's compatible jobs as one batch
of networks per group (`moex.packing`), then runs every job as the basic launcher does. Hydra
imports this module at start-up, so it imports moex only when it launches.

Options (`hydra.launcher.<key>=...`):
  max_runs: the most networks in one batch (0: no limit); a larger group is split.
  submitit: null, or the parameters of a submitit executor (e.g. `{cluster: slurm,
      slurm_partition: gpu, gpus_per_node: 1, timeout_min: 120}`): each group, and each job
      that runs alone, becomes one task of one array, writing the same folders.
"""

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.core.utils import JobReturn, configure_log, filter_overrides, run_job, setup_globals
from hydra.plugins.launcher import Launcher
from omegaconf import OmegaConf, open_dict

log = logging.getLogger(__name__)


@dataclass
class PackedLauncherConf:
    _target_: str = "hydra_plugins.moex_packed.packed_launcher.PackedLauncher"
    max_runs: int = 0
    submitit: Any = None


ConfigStore.instance().store(group="hydra/launcher", name="packed", node=PackedLauncherConf,
                             provider="moex")


class PackedLauncher(Launcher):
    def __init__(self, max_runs: int = 0, submitit: Any = None) -> None:
        self.max_runs = int(max_runs)
        self.submitit = None if submitit is None else OmegaConf.to_container(submitit)
        self.config = self.hydra_context = self.task_function = None

    def setup(self, *, hydra_context, task_function, config) -> None:
        self.config, self.hydra_context, self.task_function = config, hydra_context, task_function

    def launch(self, job_overrides, initial_job_idx) -> list[JobReturn]:
        from moex import packing

        setup_globals()
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        Path(str(self.config.hydra.sweep.dir)).mkdir(parents=True, exist_ok=True)
        configs = []
        for idx, overrides in enumerate(job_overrides, start=initial_job_idx):
            log.info("\t#%d : %s", idx, " ".join(filter_overrides(overrides)))
            sweep_config = self.hydra_context.config_loader.load_sweep_config(
                self.config, list(overrides))
            with open_dict(sweep_config):
                sweep_config.hydra.job.id = idx
                sweep_config.hydra.job.num = idx
            configs.append(sweep_config)
        planned = [packing.prepare(*self._job(c)) for c in configs]
        batches = packing.groups(planned, self.max_runs)
        if self.submitit is not None:
            return self._submit(configs, planned, batches)
        for batch in batches:
            packing.train_group(batch, _interrupted)
        return [self._run(c) for c in configs]

    def _job(self, sweep_config):
        """The typed moex config of a job and its folder."""
        from moex.cli import typed_job_config

        folder = Path(str(sweep_config.hydra.sweep.dir)) / str(sweep_config.hydra.sweep.subdir)
        return typed_job_config(sweep_config), folder

    def _run(self, sweep_config) -> JobReturn:
        """One job as the basic launcher runs it (its networks trained already, if packed)."""
        ret = run_job(hydra_context=self.hydra_context, task_function=self.task_function,
                      config=sweep_config, job_dir_key="hydra.sweep.dir",
                      job_subdir_key="hydra.sweep.subdir")
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        return ret

    def _task(self, batch_configs, batch_jobs) -> list[JobReturn]:
        """One array task: a packed batch trained, then each of its jobs run (a lone job: run)."""
        from moex import packing

        setup_globals()
        if len(batch_jobs) > 1:
            packing.train_group(batch_jobs, _interrupted)
        return [self._run(c) for c in batch_configs]

    def _submit(self, configs, planned, batches) -> list[JobReturn]:
        """Each packed batch, and each job outside one, as one task of a submitit array."""
        import submitit

        params = dict(self.submitit)
        executor = submitit.AutoExecutor(
            folder=Path(str(self.config.hydra.sweep.dir)) / ".submitit",
            cluster=params.pop("cluster", None))
        executor.update_parameters(**params)
        in_batch = {id(job): b for b, batch in enumerate(batches) for job in batch}
        tasks: dict[Any, list[int]] = {}
        for i, item in enumerate(planned):
            key = in_batch.get(id(item.job), ("alone", i))
            tasks.setdefault(key, []).append(i)
        with executor.batch():
            submitted = [(indices, executor.submit(
                self._task, [configs[i] for i in indices],
                batches[key] if not isinstance(key, tuple) else []))
                for key, indices in tasks.items()]
        returns: dict[int, JobReturn] = {}
        for indices, future in submitted:
            returns.update(zip(indices, future.result(), strict=True))
        return [returns[i] for i in range(len(configs))]


def _interrupted(jobs, exc) -> None:
    from moex.cli import interrupted_jobs

    interrupted_jobs([job.out_dir for job in jobs], exc)
