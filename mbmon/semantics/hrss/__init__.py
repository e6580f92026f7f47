"""HRSS command reconstruction: the R200/R201..R251 handshake as a lifecycle of commands.

Split along its seams: :mod:`~.spec` (``profiles/hrss_commands.toml`` as
frozen data), :mod:`~.render` (register image → command in HRSS program form),
:mod:`~.session` (:class:`HrssSession`, the device session the ``hrss``
profile names: the handshake followed from pairing steps and ticks), with
:mod:`~.steps` (what it keeps per write and command, what one step produces),
:mod:`~.reads` (what an FC 04 answer carries for it), :mod:`~.codes` (which
function codes touch which image) and :mod:`~.core` (what the compiled core asks
of the session: a mixin of it). See
``docs/commands.md``.
"""

from mbmon.semantics.hrss.render import Decoded, decode_command, decode_returns, format_scaled
from mbmon.semantics.hrss.session import HrssSession
from mbmon.semantics.hrss.spec import (
    CommandSpec,
    Field,
    Form,
    Layout,
    Spec,
    iter_layouts,
    load_spec,
    parse_spec,
)

__all__ = [
    "CommandSpec",
    "Decoded",
    "Field",
    "Form",
    "HrssSession",
    "Layout",
    "Spec",
    "decode_command",
    "decode_returns",
    "format_scaled",
    "iter_layouts",
    "load_spec",
    "parse_spec",
]
