"""dm_control's ``mjcf.Physics`` under MuJoCo 4.

dm_control 1.0.50 (the newest release) describes MuJoCo 3.17's model and data structs in a table
of array fields it binds by name; MuJoCo 4.0 removed nine of them (``flex_vertedge``,
``flexvert_J``, ...), so building any ``Physics`` fails with ``AttributeError: 'MjModel' object has
no attribute 'flex_vertedge'``. :func:`drop_missing_bindings` removes from that table the fields
the installed MuJoCo does not have; everything else binds as before. Call it once before
``mjcf.Physics.from_mjcf_model``. With MuJoCo 3.17 it removes nothing.
"""

from __future__ import annotations

import mujoco


def drop_missing_bindings() -> list[str]:
    """Remove from dm_control's binding table the array fields that the installed MuJoCo's
    ``MjModel``/``MjData`` lack; returns their names (empty when they match)."""
    from dm_control.mujoco.wrapper.mjbindings import sizes  # noqa: PLC0415 - dm_control loads OpenGL

    model = mujoco.MjModel.from_xml_string("<mujoco/>")
    structs = {"mjmodel": model, "mjdata": mujoco.MjData(model)}
    removed = []
    for struct, instance in structs.items():
        table = sizes.array_sizes[struct]
        for name in [n for n in table if not hasattr(instance, n)]:
            del table[name]
            removed.append(name)
    return removed
