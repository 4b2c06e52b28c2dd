"""The accuracy study's torque profile on the Panda arm, ``τ_i(t) = A_i sin(2π f_i t)``, as one
Fourier series (:class:`jaxbody.FourierTorque`): the frequencies 0.5, 0.7, …, 1.7 Hz are the odd
harmonics 5, 7, …, 17 of 0.1 Hz, so joint ``i`` has the single sine coefficient ``A_i`` at
harmonic ``k_i = f_i / 0.1``. ``benchmarks/work_precision.py`` and ``benchmarks/adaptive.py``
give jaxbody this effect and MuJoCo its values as ``qfrc_applied``."""

import numpy as np

#: ``A_i`` (N·m) and ``f_i`` (Hz) of the seven joints.
PANDA_AMPLITUDE = np.array([8.0, 8.0, 6.0, 6.0, 2.0, 2.0, 1.0])
PANDA_FREQUENCY = np.array([0.5, 0.7, 0.9, 1.1, 1.3, 1.5, 1.7])
#: the fundamental of the series (Hz) and the harmonic of each joint's frequency
FUNDAMENTAL = 0.1
HARMONIC = np.rint(PANDA_FREQUENCY / FUNDAMENTAL).astype(int)
assert np.allclose(HARMONIC * FUNDAMENTAL, PANDA_FREQUENCY)


def panda_torque(jb, dtype=np.float64):
    """The profile as a :class:`jaxbody.FourierTorque` (sine coefficients ``(7, 17)``)."""
    sine = np.zeros((len(PANDA_AMPLITUDE), int(HARMONIC.max())), dtype)
    sine[np.arange(len(PANDA_AMPLITUDE)), HARMONIC - 1] = PANDA_AMPLITUDE
    return jb.FourierTorque(dtype(FUNDAMENTAL), sine=sine)


def panda_torque_values(t):
    """``τ(t)`` ``(7,)`` in NumPy, for MuJoCo's ``qfrc_applied`` and the references."""
    return PANDA_AMPLITUDE * np.sin(2 * np.pi * PANDA_FREQUENCY * t)
