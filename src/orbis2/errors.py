"""The one exception family for problems a user can fix (bad input, missing files, bad params).

Stages catch it, print its message (which names the file and the fix) and exit
with status 2 instead of a stack trace; anything else is a bug and keeps its trace.
"""

from typing import Callable


class OrbisError(ValueError):
    """A user-fixable problem; the message names the file or key and the fix."""


class ConfigError(OrbisError):
    """A params.yaml value (or a model size) is missing, unknown, mistyped or impossible."""


# The exit status of a stage stopped at a checkpoint by SIGUSR1, SIGURG or SIGTERM: sysexits' EX_TEMPFAIL ("a
# temporary failure; the user is invited to retry"). Running the stage again resumes it where it stopped.
REQUEUE_EXIT = 75
# Slurm's warnings ahead of a time limit (orbis2.train.STOP_SIGNALS): a stage stopped by one asks Slurm to requeue
# its job (orbis2.stage.requeue_slurm_job); one stopped by SIGTERM (a cancel, a preemption) does not.
WARNING_SIGNALS = ("SIGUSR1", "SIGURG")


class TrainingStopped(Exception):
    """Training stopped at a step boundary on a signal (a scheduler's time limit or preemption), after writing
    its checkpoint: not an error; the stage exits with :data:`REQUEUE_EXIT` and a re-run resumes it.

    Each rank calls :meth:`stopped_together` once it is done acting on the stop, and exits after: a rank that
    exited first would end its torchrun, and srun (``--kill-on-bad-exit``) the other ranks with it, while rank 0
    may still be asking Slurm to requeue the job or ending its MLflow run."""

    def __init__(self, message: str, signal_name: str, step: int,
                 together: Callable[[], None] = lambda: None):
        super().__init__(message)
        self.signal_name, self.step = signal_name, step
        self._together = together

    def stopped_together(self) -> None:
        """Return once every rank of the run has called it (at once with one process)."""
        self._together()
