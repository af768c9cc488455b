"""A node's parameters, as rclpy's Node keeps them (the parameter half of :class:`.node.Node`).

The rules are rclpy's (node.py: declare_parameters, _apply_descriptor, get_parameter,
_set_parameters_atomically_common): a parameter declared with a value is statically typed by
that value unless its descriptor says dynamic_typing; Parameter.Type declares the type without
a value (then get_parameter raises until one is set); overrides must have the declared type; a
NOT_SET value cannot be a static default. The descriptor passed in is kept and modified (its
name and type), as rclpy does.

Setting goes through three lists of callbacks, each newest first: pre-set (set_parameters* only:
each returns a list, their concatenation is set instead), on-set (declarations too: the first
that refuses stops the set, and its reason is the result) and post-set (after the values are
stored). set_parameters runs that once per parameter, in order; set_parameters_atomically once
for the whole list, all or nothing; a declaration once per declared parameter (an on-set refusal
raises there).
"""
from __future__ import annotations

from typing import Any, Iterable, Sequence
import warnings

from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds.parameter_service import parameter_msg
from rcbf_ros.ros.dds.parameters import (
    DEPTH_RECURSIVE,
    in_range,
    InvalidParameterTypeException,
    InvalidParameterValueException,
    OnSetCallback,
    Parameter,
    parameter_descriptor,
    PARAMETER_SEPARATOR,
    ParameterAlreadyDeclaredException,
    ParameterImmutableException,
    ParameterNotDeclaredException,
    ParameterUninitializedException,
    PostSetCallback,
    PreSetCallback,
    set_parameters_result,
)


class NodeParameters:
    """Declaring, reading, setting and listing a node's parameters (rclpy's Node methods)."""

    def _init_parameters(self, *, overrides: dict[str, Parameter],
                         allow_undeclared: bool) -> None:
        """No parameters yet; ``overrides`` win over declared defaults."""
        self._parameter_overrides = overrides
        self._allow_undeclared = allow_undeclared
        self._parameters: dict[str, Parameter] = {}
        self._descriptors: dict[str, Any] = {}
        self._pre_set_parameters_callbacks: list[PreSetCallback] = []
        self._on_set_parameters_callbacks: list[OnSetCallback] = []
        self._post_set_parameters_callbacks: list[PostSetCallback] = []
        # ``/parameter_events`` (the node creates it once it can publish, as rclpy does first
        # thing): every successful declaration and set is announced there.
        self._parameter_event_publisher: Any = None

    def declare_parameter(self, name: str, value: Any = None, descriptor: Any = None,
                          ignore_override: bool = False) -> Parameter:
        """Declare ``name`` with default ``value`` (or a ``Parameter.Type``); an override wins.

        Raises:
            ParameterAlreadyDeclaredException: ``name`` was declared before.
            InvalidParameterTypeException: the override's type is not the declared type.
            ValueError: a static declaration without a type (default None or NOT_SET).
        """
        if value is None and descriptor is None:
            item: tuple = (name,)
        else:
            item = (name, value, parameter_descriptor() if descriptor is None else descriptor)
        return self.declare_parameters('', [item], ignore_override)[0]

    def declare_parameters(self, namespace: str, parameters: Iterable[tuple],
                           ignore_override: bool = False) -> list[Parameter]:
        """Declare ``(name,)``, ``(name, Parameter.Type)`` or ``(name, value, descriptor)``
        items, each as :meth:`declare_parameter`; nothing is declared if one was before."""
        descriptor_type = type(parameter_descriptor())
        declared: list[Parameter] = []
        descriptors: dict[str, Any] = {}
        for index, item in enumerate(parameters):
            if not 1 <= len(item) <= 3:
                raise TypeError(f'Invalid parameter tuple length at index {index} in parameters '
                                f'list: {item}; expecting length between 1 and 3')
            name = item[0]
            if not isinstance(name, str):
                raise TypeError(f'First element {name} at index {index} in parameters list is '
                                'not a str.')
            if namespace:
                name = f'{namespace}.{name}'
            second = item[1] if len(item) > 1 else None
            descriptor = item[2] if len(item) > 2 else parameter_descriptor()
            if not isinstance(descriptor, descriptor_type):
                raise TypeError(f'Third element {descriptor} at index {index} in parameters '
                                'list is not a ParameterDescriptor.')
            if len(item) == 1:
                warnings.warn(f"when declaring parameter named '{name}', declaring a parameter "
                              'only providing its name is deprecated', stacklevel=3)
                descriptor.dynamic_typing = True
            value = None
            if isinstance(second, Parameter.Type):
                if second is Parameter.Type.NOT_SET:
                    raise ValueError(f'Cannot declare parameter {{{name}}} as statically typed '
                                     'of type NOT_SET')
                if descriptor.dynamic_typing:
                    raise ValueError(f'When declaring parameter {{{name}}} passing a descriptor '
                                     'with `dynamic_typing=True` is not allowed when the '
                                     'parameter type is provided')
                descriptor.type = second.value
            else:
                value = second
                if not descriptor.dynamic_typing:
                    descriptor.type = Parameter.Type.from_parameter_value(value).value
                    if descriptor.type == Parameter.Type.NOT_SET.value:
                        raise ValueError('Cannot declare a statically typed parameter with '
                                         f'default value of type PARAMETER_NOT_SET ({name!r})')
            if not ignore_override and name in self._parameter_overrides:
                value = self._parameter_overrides[name].value
            declared.append(Parameter(name, value=value))
            descriptors[name] = descriptor
        already = [p.name for p in declared if p.name in self._parameters]
        if already:
            raise ParameterAlreadyDeclaredException(already)
        for parameter in declared:  # one at a time: those before a refusal stay declared
            result = self._set_parameters_common([parameter], descriptors, declaring=True)
            if not result.successful:
                if result.reason.startswith('Wrong parameter type'):
                    raise InvalidParameterTypeException(
                        parameter, Parameter.Type(descriptors[parameter.name].type).name)
                raise InvalidParameterValueException(parameter.name, parameter.value,
                                                     result.reason)
        return [self._parameters[p.name] for p in declared]

    def undeclare_parameter(self, name: str) -> None:
        """Forget a declared parameter (no callback is called).

        Raises:
            ParameterNotDeclaredException: ``name`` is not declared.
            ParameterImmutableException: it was declared read-only.
        """
        if name not in self._parameters:
            raise ParameterNotDeclaredException(name)
        if self._descriptors[name].read_only:
            raise ParameterImmutableException(name)
        del self._parameters[name]
        del self._descriptors[name]

    def _apply_descriptor(self, parameter: Parameter, descriptor: Any,
                          check_read_only: bool = True) -> Any:
        """Check ``parameter`` against ``descriptor`` (which takes its name, and its type when
        dynamically typed): read-only, type, integer and floating-point ranges; a
        SetParametersResult."""
        descriptor.name = parameter.name
        if check_read_only and descriptor.read_only:
            return set_parameters_result(
                False, f'Trying to set a read-only parameter: {parameter.name}.')
        if descriptor.dynamic_typing:
            descriptor.type = parameter.type_.value
        elif self.has_parameter(parameter.name) and parameter.type_ is Parameter.Type.NOT_SET:
            return set_parameters_result(False, 'Static parameter cannot be undeclared')
        elif (parameter.type_ is not Parameter.Type.NOT_SET
              and parameter.type_.value != descriptor.type):
            return set_parameters_result(
                False, f"Wrong parameter type, expected '{Parameter.Type(descriptor.type)}' got "
                       f"'{parameter.type_}'")
        if parameter.type_ is Parameter.Type.INTEGER and len(descriptor.integer_range):
            return in_range(parameter, descriptor.integer_range[0], integer=True)
        if parameter.type_ is Parameter.Type.DOUBLE and len(descriptor.floating_point_range):
            return in_range(parameter, descriptor.floating_point_range[0], integer=False)
        return set_parameters_result(True)

    def has_parameter(self, name: str) -> bool:
        return name in self._parameters

    def get_parameter(self, name: str) -> Parameter:
        """The declared parameter ``name``.

        Raises:
            ParameterNotDeclaredException: never declared (and undeclared ones not allowed).
            ParameterUninitializedException: statically typed and without a value.
        """
        if name in self._parameters:
            parameter = self._parameters[name]
            if (parameter.type_ is not Parameter.Type.NOT_SET
                    or self._descriptors[name].dynamic_typing):
                return parameter
            raise ParameterUninitializedException(name)
        if self._allow_undeclared:
            return Parameter(name, Parameter.Type.NOT_SET, None)
        raise ParameterNotDeclaredException(name)

    def get_parameter_or(self, name: str, alternative_value: Parameter | None = None
                         ) -> Parameter:
        """The parameter, or ``alternative_value`` if undeclared or without a value."""
        if alternative_value is None:
            alternative_value = Parameter(name, Parameter.Type.NOT_SET)
        if name not in self._parameters:
            return alternative_value
        if self._parameters[name].type_ is Parameter.Type.NOT_SET:
            return alternative_value
        return self._parameters[name]

    def get_parameters_by_prefix(self, prefix: str) -> dict[str, Parameter]:
        dotted = prefix + '.' if prefix else ''
        return {name[len(dotted):]: p for name, p in self._parameters.items()
                if name.startswith(dotted)}

    def describe_parameter(self, name: str) -> Any:
        """The descriptor kept for ``name`` (the object that was declared with)."""
        if name in self._descriptors:
            return self._descriptors[name]
        if self._allow_undeclared:
            return parameter_descriptor()
        raise ParameterNotDeclaredException(name)

    def describe_parameters(self, names: Iterable[str]) -> list[Any]:
        return [self.describe_parameter(name) for name in names]

    def set_parameters(self, parameter_list: Sequence[Parameter]) -> list[Any]:
        """Set each parameter in turn, each through the callbacks on its own; a
        SetParametersResult each. A NOT_SET value undeclares a dynamically typed parameter.

        Raises:
            ParameterNotDeclaredException: one was never declared (undeclared not allowed);
                the ones before it stay set, the ones after are not tried.
        """
        return [self._set_parameters_atomically([parameter]) for parameter in parameter_list]

    def set_parameters_atomically(self, parameter_list: Sequence[Parameter]) -> Any:
        """Set every parameter or none: the callbacks see the whole list once; one
        SetParametersResult.

        Raises:
            ParameterNotDeclaredException: one was never declared (nothing is set).
        """
        return self._set_parameters_atomically(list(parameter_list))

    def _set_parameters_atomically(self, parameter_list: list[Parameter]) -> Any:
        if self._pre_set_parameters_callbacks:
            modified: list[Parameter] = []
            for callback in list(self._pre_set_parameters_callbacks):
                modified.extend(callback(parameter_list))
            parameter_list = modified
            if not parameter_list:
                return set_parameters_result(
                    False, 'parameter list cannot be empty, this might be due to '
                           'pre_set_parameters_callback modifying the original parameters list.')
        if not all(isinstance(parameter, Parameter) for parameter in parameter_list):
            raise TypeError(f"parameter must be instance of type '{Parameter!r}'")
        undeclared = [p.name for p in parameter_list if p.name not in self._parameters]
        if undeclared and not self._allow_undeclared:
            # rclpy (7.1.1, Node._check_undeclared_parameters) finds the first undeclared name
            # with any() on a generator and lists what the generator has left: every name
            # after the first ('[]' for one). Its clients read that text; ours is the same.
            raise ParameterNotDeclaredException(undeclared[1:])
        return self._set_parameters_common(parameter_list)

    def _set_parameters_common(self, parameter_list: list[Parameter],
                               descriptors: dict[str, Any] | None = None,
                               declaring: bool = False) -> Any:
        """Descriptor checks, on-set callbacks, store, post-set callbacks: all or nothing.

        Args:
            descriptors: new descriptors of a declaration (read-only is not checked then);
                None: the stored ones.
            declaring: a NOT_SET value is stored (a declaration without a value) instead of
                undeclaring the parameter.
        """
        checking = self._descriptors if descriptors is None else descriptors
        for parameter in parameter_list:
            if parameter.name in checking:
                result = self._apply_descriptor(parameter, checking[parameter.name],
                                                check_read_only=descriptors is None)
                if not result.successful:
                    return result
        for callback in list(self._on_set_parameters_callbacks):
            result = callback(parameter_list)
            if not result.successful:
                return result
        event: dict[str, list[Parameter]] = {'new': [], 'changed': [], 'deleted': []}
        for parameter in parameter_list:
            if not declaring and parameter.type_ is Parameter.Type.NOT_SET:
                event['deleted'].append(parameter)
                self._parameters.pop(parameter.name, None)
                self._descriptors.pop(parameter.name, None)
                continue
            if descriptors is not None:
                self._descriptors[parameter.name] = descriptors[parameter.name]
            elif parameter.name not in self._descriptors:
                self._descriptors[parameter.name] = parameter_descriptor(dynamic_typing=True)
            had_value = self.get_parameter_or(parameter.name).type_ is not Parameter.Type.NOT_SET
            event['changed' if had_value else 'new'].append(parameter)
            self._parameters[parameter.name] = parameter
        self._publish_parameter_event(**event)
        for callback in list(self._post_set_parameters_callbacks):
            callback(parameter_list)
        return set_parameters_result(True)

    def _publish_parameter_event(self, *, new: list[Parameter], changed: list[Parameter],
                                 deleted: list[Parameter]) -> None:
        """One ``rcl_interfaces/msg/ParameterEvent`` of this node on ``/parameter_events``
        (before the post-set callbacks run, as rclpy publishes it)."""
        if self._parameter_event_publisher is None:
            return
        self._parameter_event_publisher.publish(
            messages.get_message('rcl_interfaces/msg/ParameterEvent')(
                stamp=self.get_clock().now().to_msg(), node=self.get_fully_qualified_name(),
                new_parameters=[parameter_msg(p) for p in new],
                changed_parameters=[parameter_msg(p) for p in changed],
                deleted_parameters=[parameter_msg(p) for p in deleted]))

    def add_pre_set_parameters_callback(self, callback: PreSetCallback) -> None:
        """Call ``callback`` first (before the older ones) on every set_parameters* (not on
        declarations); the parameters it returns are set instead, all at once."""
        self._pre_set_parameters_callbacks.insert(0, callback)

    def add_on_set_parameters_callback(self, callback: OnSetCallback) -> None:
        """Call ``callback`` first (before the older ones) before any parameters are set or
        declared; a result with ``successful=False`` refuses them with its ``reason``."""
        self._on_set_parameters_callbacks.insert(0, callback)

    def add_post_set_parameters_callback(self, callback: PostSetCallback) -> None:
        """Call ``callback`` first (before the older ones) after parameters were set or
        declared."""
        self._post_set_parameters_callbacks.insert(0, callback)

    def remove_pre_set_parameters_callback(self, callback: PreSetCallback) -> None:
        """Raises: ValueError: ``callback`` was not added."""
        self._pre_set_parameters_callbacks.remove(callback)

    def remove_on_set_parameters_callback(self, callback: OnSetCallback) -> None:
        """Raises: ValueError: ``callback`` was not added."""
        self._on_set_parameters_callbacks.remove(callback)

    def remove_post_set_parameters_callback(self, callback: PostSetCallback) -> None:
        """Raises: ValueError: ``callback`` was not added."""
        self._post_set_parameters_callbacks.remove(callback)

    def list_parameters(self, prefixes: list[str], depth: int) -> Any:
        """The declared names under ``prefixes`` (none: all) at most ``depth`` levels below
        them (:data:`DEPTH_RECURSIVE`: any), in declaration order, and the prefixes of those
        names; an ``rcl_interfaces/msg/ListParametersResult``.

        Raises:
            TypeError: ``prefixes`` is not a list of str, or ``depth`` not an int.
            ValueError: ``depth`` < 0.
        """
        if not isinstance(prefixes, list):
            raise TypeError('The prefixes argument must be a list')
        if not all(isinstance(prefix, str) for prefix in prefixes):
            raise TypeError('All prefixes must be instances of type str')
        if not isinstance(depth, int):
            raise TypeError('The depth must be instance of type int')
        if depth < 0:
            raise ValueError('The depth must be greater than or equal to zero')

        def shallow(name: str) -> bool:
            return name.count(PARAMETER_SEPARATOR) < depth

        def under(name: str, prefix: str) -> bool:
            rest = name[len(prefix) + 1:]
            return name == prefix or (name.startswith(prefix + PARAMETER_SEPARATOR) and (
                depth == DEPTH_RECURSIVE or shallow(rest)))

        everything = not prefixes and depth == DEPTH_RECURSIVE
        names: list[str] = []
        found_prefixes: list[str] = []
        for name in self._parameters:
            if not everything and not (not prefixes and shallow(name)) and not any(
                    under(name, prefix) for prefix in prefixes):
                continue
            names.append(name)
            prefix = name.rpartition(PARAMETER_SEPARATOR)[0]
            if prefix and prefix not in found_prefixes:
                found_prefixes.append(prefix)
        return messages.get_message('rcl_interfaces/msg/ListParametersResult')(
            names=names, prefixes=found_prefixes)

    def get_parameter_type(self, name: str) -> Any:
        """The type of ``name`` as rclpy gives it: the ParameterType value (an int) of a
        declared parameter, ``Parameter.Type.NOT_SET`` of an undeclared one if allowed.

        Raises:
            ParameterNotDeclaredException: never declared (and undeclared ones not allowed).
        """
        if name in self._parameters:
            return self._parameters[name].type_.value
        if self._allow_undeclared:
            return Parameter.Type.NOT_SET
        raise ParameterNotDeclaredException(name)

    def get_parameter_types(self, names: Iterable[str]) -> list[Any]:
        names = list(names)
        if not all(isinstance(name, str) for name in names):
            raise TypeError('All names must be instances of type str')
        return [self.get_parameter_type(name) for name in names]
