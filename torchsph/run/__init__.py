"""Running a case: building the simulation from it, the run loop with output, checkpoints and
progress, the threads."""
