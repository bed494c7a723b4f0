"""A stand-in for SB3's BaseCallback (see tests/fake_peers/README.md)."""


class BaseCallback:
    def __init__(self, verbose=0):
        self.model = None
        self.locals = {}

    @property
    def num_timesteps(self):
        return self.model.num_timesteps
