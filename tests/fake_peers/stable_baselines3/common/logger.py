"""A stand-in for stable_baselines3.common.logger.Logger (see tests/fake_peers/README.md)."""


class Logger:
    def __init__(self, folder, output_formats):
        self.dir, self.output_formats = folder, output_formats
