# SPDX-License-Identifier: Apache-2.0
"""magcal's evaluation, beside the product: it imports :mod:`magcal`, which never imports it.

- :mod:`~magcal_evaluation.accuracy`: the accuracy checks on seeded simulations (``make
  accuracy``, report by :mod:`~magcal_evaluation.accuracy_report`)
- :mod:`~magcal_evaluation.real`: every method on real recordings with an optical reference
  attitude, against the plain ellipsoid fit and the known-attitude floor (``make real``,
  report by :mod:`~magcal_evaluation.real_report`; the excerpt in ``evaluation/data/real``
  cut by :mod:`~magcal_evaluation.real_excerpt`)
- :mod:`~magcal_evaluation.cramer_rao`: the Cramér–Rao bound on the heading error with
  unknown translational accelerations (``make cramer-rao``, report by
  :mod:`~magcal_evaluation.cramer_rao_report`)
- :mod:`~magcal_evaluation.study`: the papers' experiments, ``magcal study``
- :mod:`~magcal_evaluation.demo`: the end-to-end demo (``make demo``) against the SIL device
  (:mod:`~magcal_evaluation.sil`) fed by the world simulator (:mod:`~magcal_evaluation.world`)

It runs from a checkout (``make setup`` installs it editable): the SIL device is built there.
"""

from pathlib import Path

#: The checkout this package runs from (evaluation/src/magcal_evaluation/ -> the repository).
REPO_ROOT = Path(__file__).resolve().parents[3]
