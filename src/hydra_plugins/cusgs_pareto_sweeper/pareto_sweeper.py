"""``hydra/sweeper=pareto``: a Hydra sweeper that runs :class:`cusgs_jax.sweep.pareto.ParetoSearch`.

Configured by ``conf/hydra/sweeper/pareto.yaml``; ``experiment=pareto_search`` uses it. Optuna is
imported only when a sweep starts (``pip install -e ".[optuna]"``).
"""

from __future__ import annotations

import logging

from hydra.core.plugins import Plugins
from hydra.plugins.sweeper import Sweeper
from omegaconf import OmegaConf

log = logging.getLogger(__name__)


class ParetoSweeper(Sweeper):
    """Optuna ask/tell over ``params`` (Hydra sweep grammar), batches run by the configured launcher."""

    def __init__(self, objectives, directions, n_trials=8, n_jobs=2, sampler=None, params=None,
                 enqueue=None, study_name=None):
        self.objectives = list(objectives)
        self.directions = list(directions)
        self.n_trials, self.n_jobs = n_trials, n_jobs
        self.sampler = sampler  # instantiated by Hydra from its _target_
        self.params = OmegaConf.to_container(params, resolve=True) if OmegaConf.is_config(params) else (params or {})
        self.enqueue = OmegaConf.to_container(enqueue, resolve=True) if OmegaConf.is_config(enqueue) else (enqueue or [])
        self.study_name = study_name
        self.config = self.launcher = self.hydra_context = None

    def setup(self, *, hydra_context, task_function, config) -> None:
        self.config, self.hydra_context = config, hydra_context
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config)

    def sweep(self, arguments):
        from cusgs_jax.sweep.pareto import ParetoSearch, distributions_from_overrides

        lines = [f"{key}={value}" for key, value in self.params.items()] + list(arguments)
        space, fixed = distributions_from_overrides(lines)
        search = ParetoSearch(self.objectives, self.directions, self.n_trials, self.n_jobs, space, fixed,
                              sampler=self.sampler, enqueue=self.enqueue, out_dir=self.config.hydra.sweep.dir,
                              study_name=self.study_name)
        log.info("Pareto search: %d trials, %d at a time, %s over %s; objectives %s",
                 search.n_trials, search.n_jobs, type(search.study.sampler).__name__, ", ".join(space),
                 ", ".join(f"{o} ({d})" for o, d in zip(self.objectives, self.directions)))

        def launch(batch, first_job):
            self.validate_batch_is_legal(batch)
            return self.launcher.launch(batch, initial_job_idx=first_job)

        front = search.run(launch)
        log.info("Pareto front (%d of %d trials), written to %s/pareto.json:", len(front), search.n_trials,
                 self.config.hydra.sweep.dir)
        for row in front:
            log.info("    job %s: %s  %s", row["job"], row["values"], row["params"])
        return front
