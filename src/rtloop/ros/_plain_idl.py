"""Stand-ins for the few ``cyclonedds.idl`` names :mod:`rtloop.ros.messages` uses.

Where cyclonedds is not installed (aarch64: no wheel) the message classes become
plain dataclasses with the same fields and type names, which the rclpy backend
converts to rclpy messages. They cannot be serialized to CDR.
"""

from typing import Any, ClassVar


class IdlStruct:
    """Plain base class recording the DDS type name given as ``typename=``."""

    __idl_typename__: ClassVar[str]

    def __init_subclass__(cls, typename: str = "", **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.__idl_typename__ = typename or cls.__name__


class sequence:  # lower case: mirrors cyclonedds.idl.types.sequence
    """``sequence[T]`` is ``list[T]``."""

    def __class_getitem__(cls, item: Any) -> Any:
        return list[item]


float64 = float
int32 = int
uint32 = int
