import sys

from softac.base.cpus import adopt_trial_settings

adopt_trial_settings()  # a sweep trial's process: its CPUs and parent, before JAX starts

from softac.cli.main import entry_point  # noqa: E402

sys.exit(entry_point())
