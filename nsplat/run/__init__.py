"""Running a task: what turns a config into a run folder, whatever the task.

* :mod:`~nsplat.run.engine` — the step loop (progress bar, TensorBoard, live-view hook, timing, atomic
  checkpoints, exact resume), the validation curve and the held-out evaluation record;
* :mod:`~nsplat.run.context` — the run folder (:class:`RunContext`: config, logs, seeds, device, threads);
* :mod:`~nsplat.run.checkpoint` — atomic writes and the checkpoint format;
* :mod:`~nsplat.run.distributed` — data-parallel training under ``torchrun`` (ranks, gradient averaging);
* :mod:`~nsplat.run.report` — the result lines a command prints on stdout.

The command line that dispatches to the tasks is :mod:`nsplat.cli`, one level up: it is the one module that sees
every room.
"""
