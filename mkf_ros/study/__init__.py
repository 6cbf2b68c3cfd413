"""The paper's simulation study (``docs/math.md`` §7) as a tool: ``mkf study``.

* :mod:`~mkf_ros.study.sim` — the procedure of §7.2 (numba): truth, measurements, convergence
  and estimation phases, common random numbers;
* :mod:`~mkf_ros.study.config` — the cells (filter × chart × update × R × rate) and selections;
* :mod:`~mkf_ros.study.runner` — work units on all cores, resumable, ``cells.csv``;
* :mod:`~mkf_ros.study.stats` — the metric and confidence intervals of §7.3;
* :mod:`~mkf_ros.study.report` — Figs. 5–7, the speed figure and the Markdown summary;
* :mod:`~mkf_ros.study.speed` — updates per second of every filter (the paper's Fig. 4);
* :mod:`~mkf_ros.study.published` — the published values of §7.5.
"""
