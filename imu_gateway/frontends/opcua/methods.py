"""The commands as OPC UA methods: their arguments, and the checks of a call before it
reaches the gateway's command path (OPC UA Part 4, 5.11.2, the Call service).

asyncua passes a call's input arguments to the method as they came, however many and of
whatever type.  Here a call is refused, and the sensor hears nothing, when:

* it names a method its object does not have: ``BadMethodInvalid``;
* it brings more arguments than the method has: ``BadTooManyArguments``;
* it brings fewer: ``BadArgumentsMissing``;
* an argument is of the wrong type: ``BadInvalidArgument``, with ``BadTypeMismatch``
  in that argument's InputArgumentResults (Part 4, Tables 67 and 68).  A Double
  argument takes any number, an Int32 one any integer (a client's HMI may send what it
  has); a String takes a String.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any

from asyncua import ua

from ...commands import CommandSpec, argument_type

Caller = Callable[..., Awaitable[Any]]
#: The command path of one sensor's command: its arguments in, the method's answer out.
Run = Callable[[dict[str, Any]], Awaitable[Any]]

_V = ua.VariantType
_INTEGERS = frozenset({_V.SByte, _V.Byte, _V.Int16, _V.UInt16, _V.Int32, _V.UInt32,
                       _V.Int64, _V.UInt64})
#: An argument's declared type, and the Variant types a call may bring for it.
ARGUMENT_TYPES: dict[type, tuple[str, frozenset[ua.VariantType]]] = {
    str: ("String", frozenset({_V.String})),
    int: ("Int32", _INTEGERS),
    float: ("Double", _INTEGERS | {_V.Float, _V.Double}),
}


def declared_type(spec: CommandSpec) -> str | None:
    """The OPC UA type of the command's argument (None: it has none)."""
    kind = argument_type(spec)
    return None if spec.argument is None else ARGUMENT_TYPES[kind or float][0]


def input_arguments(spec: CommandSpec) -> list[ua.Argument]:
    kind = declared_type(spec)
    if kind is None:
        return []
    return [ua.Argument(Name=spec.argument, DataType=ua.NodeId(getattr(ua.ObjectIds, kind)),
                        ValueRank=-1, Description=ua.LocalizedText(spec.summary))]


def _status(code: int) -> ua.StatusCode:
    return ua.StatusCode(code)


def refusal(spec: CommandSpec, args: tuple[Any, ...]) -> ua.StatusCode | ua.CallMethodResult | None:
    """Why a call with ``args`` cannot run ``spec`` (None: it can)."""
    wanted = 0 if spec.argument is None else 1
    if len(args) > wanted:
        return _status(ua.StatusCodes.BadTooManyArguments)
    if len(args) < wanted:
        return _status(ua.StatusCodes.BadArgumentsMissing)
    if wanted:
        accepted = ARGUMENT_TYPES[argument_type(spec) or float][1]
        arg = args[0]
        if not isinstance(arg, ua.Variant) or arg.VariantType not in accepted or \
                arg.is_array or arg.Value is None:
            return ua.CallMethodResult(
                StatusCode=_status(ua.StatusCodes.BadInvalidArgument),
                InputArgumentResults=[_status(ua.StatusCodes.BadTypeMismatch)])
    return None


def instance_caller(spec: CommandSpec, object_id: ua.NodeId, run: Run) -> Caller:
    """The method of one sensor: checked, then run through the command path."""
    async def call(parent: ua.NodeId, *args: Any) -> Any:
        if parent != object_id:
            return _status(ua.StatusCodes.BadMethodInvalid)
        refused = refusal(spec, args)
        if refused is not None:
            return refused
        return await run({spec.argument: args[0].Value} if spec.argument else {})
    return call


def type_caller(spec: CommandSpec, instances: dict[tuple[ua.NodeId, str], Caller]) -> Caller:
    """The type's declaration of a method.  Part 4 lets a client call it on an
    instance (the method of the object's type): it runs that sensor's own method, if
    its series has it."""
    async def call(parent: ua.NodeId, *args: Any) -> Any:
        own = instances.get((parent, spec.name))
        if own is None:
            return _status(ua.StatusCodes.BadMethodInvalid)
        return await own(parent, *args)
    return call
