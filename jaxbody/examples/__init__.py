"""The papers' worked examples as ready systems (the augmented-body paper's worked examples; defaults = the paper's reference tables)."""

from ._embedded import EmbeddedPlanarSystem as EmbeddedPlanarSystem
from .telegin import (
    CartPendulum as CartPendulum,
    OscillatingSupportPendulum as OscillatingSupportPendulum,
    VerticalLineDoublePendulum as VerticalLineDoublePendulum,
    WheelsetPendulum as WheelsetPendulum,
    cart_pendulum as cart_pendulum,
    double_pendulum as double_pendulum,
    oscillating_support_pendulum as oscillating_support_pendulum,
    three_link_manipulator as three_link_manipulator,
    vertical_line_double_pendulum as vertical_line_double_pendulum,
    wheelset_pendulum as wheelset_pendulum,
)
from .disk import (
    DiskOnPlane as DiskOnPlane,
    disk_on_plane as disk_on_plane,
    disk_outputs as disk_outputs,
    rolling_disk as rolling_disk,
    skating_disk as skating_disk,
    sliding_disk as sliding_disk,
)
