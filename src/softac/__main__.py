import sys

from softac.cpus import adopt_trial_settings

adopt_trial_settings()  # a sweep trial's process: its CPUs and parent, before JAX starts

from softac.cli import entry_point  # noqa: E402

sys.exit(entry_point())
