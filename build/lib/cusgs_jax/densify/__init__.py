"""Densification strategies, in the style of gsplat's ``strategy/``.

A strategy owns per-anchor statistics (a :class:`~cusgs_jax.model.anchors.PerAnchor`
pytree kept in ``TrainState.densify[strategy.name]``) and is called at two hooks:

* ``accumulate(stats, view) -> stats`` — inside the jitted train step, once per
  rendered view (:class:`cusgs_jax.densify.base.ViewRecord`);
* ``due(step) -> bool`` and ``update(state, tx, step) -> (state, info)`` — on the
  host between steps, after ``step`` completed steps; may refill dead slots,
  clear ``alive`` bits or grow the capacity (always through :mod:`cusgs_jax.densify.ops`).

Strategies: :class:`~cusgs_jax.densify.scaffold.ScaffoldStrategy` (growing + opacity
pruning) and :class:`~cusgs_jax.densify.feature_prune.FeaturePruneStrategy`
(CUS-GS feature-aware pruning). :func:`cusgs_jax.densify.base.make_strategies` builds
the ones a configuration asks for.
"""
