"""Densification strategies, in the style of gsplat's ``strategy/``.

A strategy owns per-anchor statistics (a :class:`~cusgs_jax.model.anchors.PerAnchor`
pytree kept in ``TrainState.densify[strategy.name]``) and is called at two hooks:

* ``accumulate(stats, view) -> stats`` — inside the jitted train step, once per
  rendered view (:class:`cusgs_jax.densify.base.ViewRecord`);
* ``due(step) -> bool`` and ``update(state, tx, step) -> (state, UpdateInfo)`` — on the
  host between steps, after ``step`` completed steps; may refill dead slots,
  clear ``alive`` bits or grow the capacity (always through :mod:`cusgs_jax.densify.ops`);
* optional, no-op by default (:class:`cusgs_jax.densify.base.Strategy`):
  ``before_first_update(probe)`` once before the first update, ``log_values(tally)`` and
  ``results(tally)`` for the keys the strategy adds to ``metrics.jsonl`` and ``eval.json``.

The run loop calls these for every strategy alike and records each one's
:class:`~cusgs_jax.densify.base.Tally` (``densify`` in ``metrics.jsonl`` and ``eval.json``).

Strategies: :class:`~cusgs_jax.densify.scaffold.ScaffoldStrategy` (growing + opacity
pruning) and :class:`~cusgs_jax.densify.feature_prune.FeaturePruneStrategy`
(CUS-GS feature-aware pruning). :func:`cusgs_jax.densify.factory.make_strategies` builds
the ones a configuration asks for.
"""
