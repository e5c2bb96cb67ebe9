"""Sim-to-real gap diagnosis: where the gap lies, which unmodelled effect causes it, and
how far it shrinks once modelled (checked on held-out data).

Public API::

    from crisp_gym.sim2real import RealLog, load_log, save_log, diagnose, DiagnoseConfig, write_report
    result = diagnose([(log, spec)], holdout=None)  # Diagnosis: verdict, where, ranking, selected, ...
    # the model as an MjSpec (a compiled MjModel also works; effects that add parts are then skipped)
    write_report(result, "report_dir")

The command line is :mod:`crisp_gym.sim2real.cli` (``crisp gap diagnose`` / ``crisp gap bench``).
"""

from crisp_gym.sim2real.diagnose import DiagnoseConfig, Diagnosis, diagnose
from crisp_gym.sim2real.log import RealLog, load_log, save_log, validate_against_model
from crisp_gym.sim2real.recorder import LogRecorder
from crisp_gym.sim2real.report import write_report

__all__ = ["DiagnoseConfig", "Diagnosis", "LogRecorder", "RealLog", "diagnose", "load_log", "save_log", "validate_against_model",
           "write_report"]
