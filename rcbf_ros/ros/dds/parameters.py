"""rclpy's parameter types over the Cyclone runtime: ``Parameter``, its exceptions, descriptors.

What a node does with them (declaring, setting, callbacks) is :mod:`.node_parameters`; what
travels over the parameter services is :mod:`.parameter_service`.
"""
from __future__ import annotations

import array
import enum
import math
from typing import Any, Callable

from rcbf_ros.ros.dds import messages


class ParameterException(Exception):
    """Base of the parameter errors (rclpy.exceptions')."""

    def __init__(self, error_msg: str, parameters: str | list[str]) -> None:
        super().__init__(f'{error_msg}: {parameters}')


class ParameterNotDeclaredException(ParameterException):
    """get_parameter() / set_parameters() of a name that was never declared."""

    def __init__(self, parameters: str | list[str]) -> None:
        super().__init__('Invalid access to undeclared parameter(s)', parameters)


class ParameterAlreadyDeclaredException(ParameterException):
    """declare_parameter() twice for one name."""

    def __init__(self, parameters: str | list[str]) -> None:
        super().__init__('Parameter(s) already declared', parameters)


class InvalidParameterTypeException(ParameterException):
    """A value (an override, or a set) of another type than the parameter's static type."""

    def __init__(self, desired_parameter: Parameter, expected_type: str) -> None:
        value = desired_parameter.value
        super().__init__(
            f"Trying to set parameter '{desired_parameter.name}' to '{value}' of type "
            f"'{Parameter.Type.from_parameter_value(value).name}', expecting type "
            f"'{expected_type}'", desired_parameter.name)


class InvalidParameterValueException(ParameterException):
    """A value refused for another reason than its type (e.g. undeclaring a static one)."""

    def __init__(self, parameter: str, value: Any, reason: str) -> None:
        super().__init__(f'Invalid parameter value ({value}) for parameter. Reason: {reason}',
                         parameter)


class ParameterUninitializedException(ParameterException):
    """get_parameter() of a statically typed parameter that has no value."""

    def __init__(self, parameter_name: str) -> None:
        super().__init__(f"The parameter '{parameter_name}' is not initialized", parameter_name)


class ParameterImmutableException(ParameterException):
    """undeclare_parameter() of a read-only parameter."""

    def __init__(self, parameter_name: str) -> None:
        super().__init__('Attempted to modify read-only parameter', parameter_name)


class Parameter:
    """rclpy.parameter.Parameter: ``name``, ``type_``, ``value`` (NOT_SET: ``None``)."""

    class Type(enum.Enum):
        """rclpy.parameter.Parameter.Type (values: rcl_interfaces/msg/ParameterType)."""

        NOT_SET = 0
        BOOL = 1
        INTEGER = 2
        DOUBLE = 3
        STRING = 4
        BYTE_ARRAY = 5
        BOOL_ARRAY = 6
        INTEGER_ARRAY = 7
        DOUBLE_ARRAY = 8
        STRING_ARRAY = 9

        @classmethod
        def from_parameter_value(cls, value: Any) -> Parameter.Type:
            """The type rclpy infers from a Python value (an empty list is a BYTE_ARRAY).

            Raises:
                TypeError: no parameter type holds the value.
            """
            if value is None:
                return cls.NOT_SET
            if isinstance(value, bool):
                return cls.BOOL
            if isinstance(value, int):
                return cls.INTEGER
            if isinstance(value, float):
                return cls.DOUBLE
            if isinstance(value, str):
                return cls.STRING
            if isinstance(value, (list, tuple, array.array)):
                for kind, item_types in ((cls.BYTE_ARRAY, bytes), (cls.BOOL_ARRAY, bool),
                                         (cls.INTEGER_ARRAY, int), (cls.DOUBLE_ARRAY, float),
                                         (cls.STRING_ARRAY, str)):
                    if all(isinstance(v, item_types) for v in value):
                        return kind
                raise TypeError(f"The given value is not a list of one of the allowed types "
                                f"'{value}'.")
            raise TypeError(f"The given value is not one of the allowed types '{value}'.")

        def check(self, value: Any) -> bool:
            """True if ``value`` is a value of this type."""
            if self is Parameter.Type.NOT_SET:
                return value is None
            scalar = {Parameter.Type.BOOL: bool, Parameter.Type.INTEGER: int,
                      Parameter.Type.DOUBLE: float, Parameter.Type.STRING: str}.get(self)
            if scalar is not None:
                return isinstance(value, scalar)
            if self is Parameter.Type.BYTE_ARRAY:
                return isinstance(value, (list, tuple)) and all(
                    isinstance(v, bytes) and len(v) == 1 for v in value)
            item = {Parameter.Type.BOOL_ARRAY: bool, Parameter.Type.INTEGER_ARRAY: int,
                    Parameter.Type.DOUBLE_ARRAY: float, Parameter.Type.STRING_ARRAY: str}[self]
            containers = ((list, tuple, array.array) if item in (int, float)
                          else (list, tuple))
            return isinstance(value, containers) and all(isinstance(v, item) for v in value)

    def __init__(self, name: str, type_: Parameter.Type | None = None,
                 value: Any = None) -> None:
        if type_ is None:
            type_ = Parameter.Type.from_parameter_value(value)
        if not isinstance(type_, Parameter.Type):
            raise TypeError(f"type must be an instance of '{Parameter.Type!r}'")
        if not type_.check(value):
            raise ValueError(f"Type '{type_}' and value '{value}' do not agree")
        self._name = name
        self._type = type_
        self._value = value

    @property
    def name(self) -> str:
        return self._name

    @property
    def type_(self) -> Parameter.Type:
        return self._type

    @property
    def value(self) -> Any:
        return self._value

    def __repr__(self) -> str:
        return f'Parameter({self.name!r}, {self.type_.name}, {self.value!r})'


def parameter_descriptor(**fields: Any) -> Any:
    """A new ``rcl_interfaces/msg/ParameterDescriptor`` (rclpy's class of that name)."""
    return messages.get_message('rcl_interfaces/msg/ParameterDescriptor')(**fields)


def set_parameters_result(successful: bool, reason: str = '') -> Any:
    """A new ``rcl_interfaces/msg/SetParametersResult``."""
    return messages.get_message('rcl_interfaces/msg/SetParametersResult')(
        successful=successful, reason=reason)


PARAMETER_SEPARATOR = '.'
"""What separates the levels of a parameter name (rclpy's PARAMETER_SEPARATOR_STRING)."""
DEPTH_RECURSIVE = 0
"""``list_parameters`` depth that lists every level (rcl_interfaces/srv/ListParameters)."""
PARAM_REL_TOL = 1e-6
"""Relative tolerance of a floating-point range's edges and steps (rclpy's Node.PARAM_REL_TOL)."""

def in_range(parameter: Parameter, bounds: Any, *, integer: bool) -> Any:
    """A SetParametersResult: ``parameter`` within an Integer/FloatingPointRange, on a step.

    The edges are always in; a floating-point value within :data:`PARAM_REL_TOL` of an edge or
    of a step counts as on it.
    """
    low, high = sorted((bounds.from_value, bounds.to_value))
    value = parameter.value

    def close(a: float, b: float) -> bool:
        return a == b if integer else math.isclose(a, b, rel_tol=PARAM_REL_TOL)

    if close(value, low) or close(value, high):
        return set_parameters_result(True)
    if not low < value < high:
        dot = '.' if integer else ''
        return set_parameters_result(
            False, f'Parameter {parameter.name} out of range{dot} Min: {low}, Max: {high}, '
                   f'value: {value}')
    if bounds.step == 0:
        return set_parameters_result(True)
    if integer:
        on_step = (value - low) % bounds.step == 0
        text = 'is not a valid step'
    else:
        on_step = close(low + round((value - low) / bounds.step) * bounds.step, value)
        text = 'is not close enough to a valid step'
    if on_step:
        return set_parameters_result(True)
    return set_parameters_result(
        False, f'The parameter value for {parameter.name} {text}. Min: {low}, max: {high}, '
               f'value: {value}, step: {bounds.step}')


PreSetCallback = Callable[[list[Parameter]], list[Parameter]]
"""Gets the parameters about to be set; returns the list to set instead (all at once)."""
OnSetCallback = Callable[[list[Parameter]], Any]
"""Gets the parameters about to be set; returns a SetParametersResult (False: refuse all)."""
PostSetCallback = Callable[[list[Parameter]], None]
"""Gets the parameters that were just set."""
