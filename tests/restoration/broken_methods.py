"""Methods of one's own that break the protocol at call time (the tests of the guard,
:func:`restoration.run_method`, load them by this file's path)."""

import numpy as np

from restoration import Calibration, RestoredView, RestoreResult, SurfaceOptions


class Base:
    calibration_type = Calibration
    options_type = SurfaceOptions

    def __init__(self, options=None):
        self.options = options or SurfaceOptions()


class Raises(Base):
    name = "raises"

    def __call__(self, images, cal, track=None):
        raise RuntimeError("a bug of mine")


class ReturnsNone(Base):
    name = "returns-none"

    def __call__(self, images, cal, track=None):
        return None


class WrongShape(Base):
    name = "wrong-shape"

    def __call__(self, images, cal, track=None):
        return RestoreResult(self.name, view=RestoredView(np.zeros((5, 5, 3)),
                                                          np.ones((5, 5), bool)))


class Exits(Base):
    name = "exits"

    def __call__(self, images, cal, track=None):
        raise SystemExit(3)
