"""One module per model structure, each with ``fit(dataset, rows) -> fitted`` and the
``candidate`` that the identification's registry (:data:`calibration.identify.REGISTRY`) calls:

- :mod:`.ridge_bank`: ridge over n, n² (and the inputs) through banks of exact first-order
  filters; α chosen by cross-validation on the folds; the runtime's state-space model;
- :mod:`.baseline`: the exponential baseline (one time constant chosen by CV, S∞ quadratic in n),
  the bar every other candidate must clear;
- :mod:`.output_error`: the physical output-error form (a thermal state whose dissipation
  depends on speed, plus an elastic term);
- :mod:`.paper_ols`: the paper's one-step OLS, scored in free run for the comparison.

Every estimator fits on the measured rows of ``rows`` of a :class:`calibration.dataset.Dataset`
and free-runs the whole dataset; the folds, the metrics and the choice are shared
(:mod:`calibration.folds`, :mod:`calibration.metrics`, :mod:`calibration.identify`).
"""
