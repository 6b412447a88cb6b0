# SPDX-License-Identifier: Apache-2.0
"""``magcal study``: the papers' experiments, reproducible.

:func:`magcal_evaluation.study.run.run_study` runs the experiments of
:mod:`magcal_evaluation.study.experiments` (Kok & Schön's Figure 8, Zhao et al.'s Table 1 and
Figure 1, a comparison of every method) through the resumable runner of
:mod:`magcal_evaluation.study.runner`, then writes ``summary.md`` and the PNGs of
:mod:`magcal_evaluation.study.summary` into the study folder.

This package imports none of them: magcal's command line loads
:mod:`magcal_evaluation.study.command` for every ``magcal --help``, and the experiments load
the whole numerical stack and matplotlib.
"""
