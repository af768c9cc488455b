"""The body of every node's ``main()``: the Jazzy pattern, written once.

``rclpy.init`` -> build the node -> spin -> Ctrl-C / SIGTERM end it quietly -> the node's own
exit work -> ``destroy_node`` -> ``rclpy.try_shutdown``. Each node keeps a one-line ``main``
that says what differs. ``--help`` answers before anything starts, and SIGINT / SIGTERM are
handled here rather than by the middleware, so that a callback under way finishes with a
valid context and the exit work is never cut short.

Help, stopping and ``python -m rcbf_ros.ros.node_main``:
docs/NODES.md#every-nodes-main-help-and-stopping
"""
from __future__ import annotations

import functools
import importlib
import os
import re
import signal
import sys
import threading
import time
import traceback
from typing import Any, Callable, Sequence, TypeVar

from rcbf_ros.node_logic.interface import (
    help_text,
    InterfaceSource,
    parameter_specs,
    parameter_type,
    ParameterSpec,
    resolve,
    wants_help,
)
from rcbf_ros.node_logic.sim_clock import ClockGuard
from rcbf_ros.parameters.reader import parameters_of, read_parameters
from rcbf_ros.ros.console import console_line, run_writing_stdout

T = TypeVar('T')

INTERRUPTED_EXIT = 130
"""Exit status of a node stopped by SIGINT before it started (128 + SIGINT, as a shell says)."""
SPIN_SLICE_S = 0.1
"""Longest wait of :func:`spin` for work: bounds how late a stop request is noticed."""
_ASKED = -1
"""The recorded "signal" of :func:`request_stop`: stop without an exception."""


def stop_signals(taken: Any = ()) -> tuple[int, ...]:
    """The signals that ask a process to stop cleanly: SIGINT, SIGTERM and SIGHUP (a terminal
    closing, a dropped ssh connection: without a handler the process ends at once, its exit work
    undone), SIGHUP only where it is not ignored (nohup) or already in ``taken``."""
    hangup = getattr(signal, 'SIGHUP', None)
    if hangup is None or (hangup not in taken and signal.getsignal(hangup) == signal.SIG_IGN):
        return (signal.SIGINT, signal.SIGTERM)
    return (signal.SIGINT, signal.SIGTERM, hangup)


class _StopRequest:
    """SIGINT / SIGTERM / SIGHUP as a request to stop between callbacks (see the module
    docstring); SIGHUP is taken as SIGTERM."""

    def __init__(self) -> None:
        self.signum: int | None = None
        """The signal received (or :data:`_ASKED`), None while running."""
        self.deferring = False
        """Inside :func:`spin_once`: a signal is only recorded."""
        self.ignoring = False
        """The node is stopping: signals are ignored."""
        self._previous: dict[int, Any] = {}

    def reset(self) -> None:
        self.signum, self.deferring, self.ignoring = None, False, False

    def install(self) -> None:
        """Take SIGINT, SIGTERM and SIGHUP (main thread only; elsewhere signals cannot be
        handled). SIGHUP stays ignored where the process started with it ignored (nohup)."""
        if threading.current_thread() is not threading.main_thread():
            return
        for signum in stop_signals(self._previous):
            previous = signal.signal(signum, self.on_signal)
            self._previous.setdefault(signum, previous)

    def restore(self) -> None:
        """Give the signals back to the handlers they had before :meth:`install`."""
        if threading.current_thread() is not threading.main_thread():
            return
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def on_signal(self, signum: int, frame: Any) -> None:
        if self.ignoring or self.signum is not None:
            return  # already stopping: let it finish
        self.signum = signum
        if not self.deferring:
            self.raise_if_signalled()

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def raise_if_signalled(self) -> None:
        """Raise what the received signal asks for (nothing after :func:`request_stop`)."""
        if self.signum == signal.SIGINT:
            raise KeyboardInterrupt
        if self.signum is not None and self.signum != _ASKED:
            from rcbf_ros.ros.runtime import ExternalShutdownException
            raise ExternalShutdownException(f'received signal {signal.Signals(self.signum).name}')


_STOP = _StopRequest()


def request_stop() -> None:
    """Ask the running node to stop after the current callback (e.g. its work is done): the
    exit work, ``destroy_node`` and the shutdown follow as after Ctrl-C, with exit status 0."""
    if _STOP.signum is None:
        _STOP.signum = _ASKED


def stop_requested() -> bool:
    """Whether a signal or :func:`request_stop` asked the node to stop."""
    return _STOP.requested


def parameter_descriptor(spec: ParameterSpec | None, *, dynamic_typing: bool = False,
                         read_only: bool = False, description: str = '') -> Any:
    """The ParameterDescriptor of a parameter declared from ``spec``: its one-line description
    (``description`` when there is no spec) and, for a number with bounds, its
    FloatingPointRange or IntegerRange (:attr:`ParameterSpec.range`), so that ``ros2 param
    describe`` shows what ``--help`` prints and the middleware refuses a value outside the
    range before any callback runs. A new descriptor per call: rclpy keeps and modifies the
    one it is given."""
    from rcbf_ros.ros.runtime import get_message, ParameterDescriptor
    descriptor = ParameterDescriptor(
        dynamic_typing=dynamic_typing, read_only=read_only,
        description=spec.description if spec is not None else description)
    bounds = None if spec is None else spec.range
    if bounds is not None and spec.type == 'double':
        descriptor.floating_point_range = [get_message('rcl_interfaces/msg/FloatingPointRange')(
            from_value=float(bounds[0]), to_value=float(bounds[1]), step=0.0)]
    elif bounds is not None:
        descriptor.integer_range = [get_message('rcl_interfaces/msg/IntegerRange')(
            from_value=int(bounds[0]), to_value=int(bounds[1]), step=0)]
    return descriptor


RUNTIME_PARAMETERS = ('use_sim_time', 'start_type_description_service')
"""Parameters the runtime declares itself (rclpy's, and ours as rclpy), with its own
descriptors: :func:`declare_specs` leaves them alone."""
OTHER_DESCRIPTION = 'not read by this node (given on its command line or in a params file)'
"""The description of a parameter an override declared that no spec of the node names."""


def read_at_start(name: str) -> bool:
    """The default ``read_only`` of :func:`declare_specs`: every parameter is read once, as the
    node starts, so every one is declared read-only and the runtime refuses a set of it (a set
    it took would report success, and ``ros2 param get`` show a value the node does not use)."""
    return True


def declare_specs(node: Any, specs: Sequence[ParameterSpec], *,
                  given: Sequence[ParameterSpec] = (), dynamic_typing: bool = False,
                  dynamic_overrides: bool = False,
                  read_only: Callable[[str], bool] | None = read_at_start,
                  others: str | Callable[[str], str | None] | None = OTHER_DESCRIPTION
                  ) -> None:
    """Declare ``node``'s parameters from ``specs``: the one way the nodes declare them.

    Every declaration gets a descriptor of its own (:func:`parameter_descriptor`: the spec's
    one line and range; rclpy keeps and modifies the one it is given):

    - a spec of fixed name not declared yet is declared with its default: a default of None
      declares no type (dynamically typed, as rclpy declares a name given alone); a string list
      without a default is declared as STRING_ARRAY by type (rclpy types an empty list as a
      BYTE_ARRAY, which refuses ``-p topics:=[/a]``, and a params file cannot hold an empty
      list: rcl reads ``[]`` as no value);
    - a parameter declared already without a description (by an override, in a node made with
      ``automatically_declare_parameters_from_overrides``) is declared again with its value, as
      the override declared it (typed by its value, or of any type with
      ``dynamic_overrides``), and the descriptor of the spec of ``specs`` or ``given`` that
      names it (a ``<name>`` pattern too), else with ``others`` as its description (a function
      of the name: its description; None: left as it is, for a call that declares part of a
      node's parameters, or for a name the function returns None for). An override outside the
      spec's range is left as it was declared: the node's reader refuses it, one line naming
      the key, as it reads its settings.

    ``given``: specs of parameters declared only when given (the filter keys a node reads from a
    params file). ``dynamic_typing``: the declarations from defaults take a value of any type
    (else only those without a default). ``read_only``: whether the parameter of a name is
    fixed at start (its descriptor read-only, so that the runtime refuses a set of it);
    by default every one is (:func:`read_at_start`): a node that reads some at runtime names
    them and checks their new values as at start in an on-set callback, as the safety filter
    does; None: none is. :data:`RUNTIME_PARAMETERS` are left as the runtime declared them.

    Raises:
        ValueError: one line naming the parameter: a declaration the runtime refuses (e.g. a
            default outside the declared range, an override of another type).
    """
    from rcbf_ros.ros.runtime import Parameter, ParameterException

    try:
        for spec in specs:
            if spec.pattern or node.has_parameter(spec.name):
                continue
            descriptor = parameter_descriptor(
                spec, dynamic_typing=dynamic_typing or spec.default is None,
                read_only=read_only is not None and read_only(spec.name))
            if spec.type == 'string[]' and not spec.default and not descriptor.dynamic_typing:
                node.declare_parameter(spec.name, Parameter.Type.STRING_ARRAY, descriptor)
            else:
                node.declare_parameter(spec.name, spec.default, descriptor)
        for name, parameter in node.get_parameters_by_prefix('').items():
            if name in RUNTIME_PARAMETERS or node.describe_parameter(name).description:
                continue
            spec = next((s for s in (*specs, *given) if s.matches(name)), None)
            other = others(name) if callable(others) else others
            if spec is None and other is None:
                continue
            value = parameter.value
            if spec is not None and spec.range_refuses(value):
                continue  # as the override declared it: the node's reader refuses it
            node.undeclare_parameter(name)
            node.declare_parameter(name, value, parameter_descriptor(
                spec, dynamic_typing=dynamic_overrides or value is None,
                read_only=read_only is not None and read_only(name),
                description=other or ''), ignore_override=True)
    except ParameterException as exc:
        raise ValueError(str(exc)) from exc


def declare_settings(node: Any, cls: type[T]) -> T:
    """Declare every parameter of the dataclass ``cls`` on ``node`` (:func:`declare_specs`)
    and read them into it; string lists read as empty while unset, their empty strings dropped.

    Raises:
        ValueError: one line naming the parameter (a declaration the runtime refuses, or a
            value the typed reader refuses).
    """
    from rcbf_ros.ros.runtime import Parameter

    declare_specs(node, parameter_specs(cls, mark_read_only=False))
    values = {}
    for parameter in parameters_of(cls):
        key = parameter.key
        if parameter_type(parameter.kind) == 'string[]':
            unset = Parameter(key, Parameter.Type.STRING_ARRAY, [])
            values[key] = [str(v) for v in node.get_parameter_or(key, unset).value if str(v)]
        else:
            values[key] = node.get_parameter(key).value
    return read_parameters(cls, values)


def spin_once(node: Any, *, timeout_sec: float | None = SPIN_SLICE_S) -> None:
    """Run at most one callback of ``node``; a signal received meanwhile lets it finish, then
    raises (``KeyboardInterrupt`` for SIGINT, ``ExternalShutdownException`` for SIGTERM)."""
    from rcbf_ros.ros.runtime import rclpy
    _STOP.raise_if_signalled()
    _STOP.deferring = True
    try:
        rclpy.spin_once(node, timeout_sec=timeout_sec)
    finally:
        _STOP.deferring = False
    _STOP.raise_if_signalled()


def spin(node: Any) -> None:
    """Run ``node``'s callbacks until :func:`request_stop`, a shutdown or a signal (raises)."""
    from rcbf_ros.ros.runtime import rclpy
    while rclpy.ok() and not _STOP.requested:
        spin_once(node)
    _STOP.raise_if_signalled()


def _init_options() -> dict[str, Any]:
    """``rclpy.init`` keywords that keep the middleware's signal handlers out."""
    from rcbf_ros.ros.runtime import USING_RCLPY
    if not USING_RCLPY:
        return {}
    from rclpy.signals import SignalHandlerOptions
    return {'signal_handler_options': SignalHandlerOptions.NO}


def _init_errors() -> tuple[type[BaseException], ...]:
    """What ``rclpy.init`` raises for a bad command line or params file: ValueError on our
    runtime, rcl's ``RCLError`` ("failed to initialize rcl: ...") on real rclpy."""
    from rcbf_ros.ros.runtime import USING_RCLPY
    if not USING_RCLPY:
        return (ValueError,)
    from rclpy.impl.implementation_singleton import rclpy_implementation
    return (ValueError, rclpy_implementation.RCLError)


def init_error_line(error: BaseException) -> str:
    """rcl's error text on one line: its ``, at <source file>:<line>`` trail dropped."""
    text = ' '.join(str(error).split())
    return text.split(', at /', 1)[0].rstrip()


def print_help(interface: InterfaceSource, argv: Sequence[str]) -> int:
    """Print the ``--help`` of ``interface`` for the command line ``argv``; exit status 0 (a
    stdout that fails: :func:`run_writing_stdout`)."""
    resolved = resolve(interface, argv)

    def write() -> int:
        sys.stdout.write(help_text(resolved))
        return 0
    return run_writing_stdout(resolved.node, write)


LIGHT_INTERFACES: dict[str, str] = {
    'rcbf_ros.ros.safety_filter_node': 'rcbf_ros.node_logic.safety_filter_interface',
}
"""Node module -> the module that holds its ``INTERFACE`` without the node class, and so
without the middleware its class derives from: its ``--help`` is answered from there
(:func:`main_of`, :func:`run_module`) without loading the DDS runtime."""


def _light_interface(module: str, argv: Sequence[str]) -> InterfaceSource | None:
    """The ``INTERFACE`` of node module ``module`` when ``argv`` asks for the help and
    :data:`LIGHT_INTERFACES` names where it lives; else None (the node module answers)."""
    light = LIGHT_INTERFACES.get(module)
    if light is None or not wants_help(argv):
        return None
    return importlib.import_module(light).INTERFACE


def main_of(module: str, args: Sequence[str] | None = None) -> int:
    """A node's console script: ``-h`` / ``--help`` from :data:`LIGHT_INTERFACES`'s module of
    node module ``module`` when it has one, before the node module (and the middleware) is
    imported; otherwise the node module's ``main(args)``."""
    argv = list(sys.argv if args is None else args)
    interface = _light_interface(module, argv)
    if interface is not None:
        return print_help(interface, argv)
    return importlib.import_module(module).main(args)


def safety_filter(args: Sequence[str] | None = None) -> int:
    """The console script ``safety_filter`` (:mod:`rcbf_ros.ros.safety_filter_node`)."""
    return main_of('rcbf_ros.ros.safety_filter_node', args)


def run_node(name: str, make_node: Callable[[], Any], args: Sequence[str] | None = None, *,
             run: Callable[[Any], None] | None = None,
             on_exit: Callable[[Any], None] | None = None,
             setup_errors: tuple[type[BaseException], ...] = (),
             setup_message: str = 'invalid parameters: ',
             interface: InterfaceSource | None = None) -> int:
    """Run one node until it finishes or Ctrl-C / SIGTERM; the console script's exit status.

    Args:
        name: the node's name, for the error line (the node may not exist yet).
        make_node: builds the node (reads and checks its parameters).
        args: command line (None: ``sys.argv``, passed explicitly so every runtime reads it).
        run: drives the node (default :func:`spin`; one of its own uses :func:`spin_once`).
        on_exit: the node's exit work, before ``destroy_node`` (also after Ctrl-C / SIGTERM).
        setup_errors: exceptions of ``make_node`` that are the user's: printed as
            ``<name>: <setup_message><error>`` on stderr, exit status 2. An ArithmeticError
            of ``make_node`` (an overflow of a number no bound refused) is printed so too,
            with its type and place (:func:`arithmetic_error_line`).
        setup_message: the middle of that line ('' for none).
        interface: the node's topics and parameters, printed by ``-h`` / ``--help``.

    Returns:
        0, or 2 on a setup error (including a bad ``--ros-args`` section or params file, which
        ``rclpy.init`` refuses). Other exceptions, and any raised once the node is built,
        propagate (after the shutdown).
    """
    argv = list(sys.argv if args is None else args)
    if interface is not None and wants_help(argv):
        return print_help(interface, argv)
    from rcbf_ros.ros.runtime import ExternalShutdownException, ParameterException, rclpy

    _STOP.reset()
    _STOP.install()
    try:
        try:
            rclpy.init(args=argv, **_init_options())
        except _init_errors() as exc:
            console_line(f'{name}: {init_error_line(exc)}')
            return 2
        except (KeyboardInterrupt, ExternalShutdownException):
            _STOP.ignoring = True
            rclpy.try_shutdown()
            return 0
        _STOP.install()  # our runtime's init installs handlers of its own
        # A parameter the runtime declares for every node (use_sim_time) refusing its override
        # is the user's error too.
        built = None if interface is None else functools.partial(
            warn_unknown_parameters, argv=argv, interface=interface)
        return _run(name, make_node, built=built, run=run, on_exit=on_exit,
                    setup_errors=(*setup_errors, ParameterException),
                    setup_message=setup_message, shutdown_errors=(ExternalShutdownException,),
                    rclpy=rclpy, argv=argv)
    finally:
        _STOP.restore()


ERROR_LINE_LIMIT = 240
"""Most characters of the error text in a setup error's line."""


def arithmetic_error_line(error: ArithmeticError) -> str:
    """An overflow (or other ArithmeticError) while a node is built, on one line: its type,
    its text and where it was raised (function, file and line).

    Building a node reads its parameters, and a number out of every range the code expects
    (``rate_hz:=1e-300`` -> a period of inf) ends as such an error where no declared bound
    refused it first: that is a bad input, exit status 2 without a traceback. It may also be a
    programming error, which is why the line says where it was raised rather than only
    'invalid': the place names the bound that is missing.
    """
    text = ' '.join(str(error).split())[:ERROR_LINE_LIMIT]
    frames = traceback.extract_tb(error.__traceback__)
    if not frames:
        return f'{type(error).__name__}: {text}'
    last = frames[-1]
    return (f'{type(error).__name__}: {text} (in {last.name}, '
            f'{_shown_path(last.filename)}:{last.lineno}: a number out of range)')


def _shown_path(filename: str) -> str:
    """``filename`` from the package's parent directory when it is inside it, else as is."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    path = os.path.abspath(filename)
    return os.path.relpath(path, root) if path.startswith(root + os.sep) else filename


def unknown_parameters(node_name: str, fully_qualified: str, argv: Sequence[str],
                       interface: InterfaceSource) -> list[str]:
    """The WARN lines of :func:`rcbf_ros.parameters.unknown.unknown_parameter_lines` for the
    node of ``interface`` and its command line ``argv``: parameters given to it that it does not
    read (a key under ``/**`` may be one of the shared problem's: the safety filter's)."""
    from rcbf_ros.node_logic.safety_filter_interface import INTERFACE as SHARED
    from rcbf_ros.parameters.arguments import parse_ros_arguments
    from rcbf_ros.parameters.unknown import names_of, unknown_parameter_lines
    own = resolve(interface, argv)
    rules = parse_ros_arguments(argv).parameter_rules
    repeated = [f'{line} (read as ROS 2 reads it: the later value of the same type)'
                for line in rules.repeated_keys]
    return repeated + unknown_parameter_lines(
        sections=rules.sections(), node_name=node_name,
        fully_qualified=fully_qualified, own=lambda name: own.spec(name) is not None,
        shared=lambda name: SHARED.spec(name) is not None, own_names=names_of(own.parameters),
        shared_names=names_of(SHARED.parameters))


def warn_unknown_parameters(node: Any, argv: Sequence[str], interface: InterfaceSource
                            ) -> None:
    """Log :func:`unknown_parameters` of a node just built, one WARN per line. A help to the
    user, never a reason to stop: a failure to work them out is logged as a WARN too."""
    try:
        lines = unknown_parameters(node.get_name(), node.get_fully_qualified_name(), argv,
                                   interface)
    except Exception as exc:  # noqa: BLE001 - the node runs on; say why nothing was checked
        lines = [f'parameters given not checked against those read: {type(exc).__name__}: '
                 f'{" ".join(str(exc).split())[:ERROR_LINE_LIMIT]}']
    for line in lines:
        node.get_logger().warning(line)


EMPTY_VALUE = ('an empty list or map has no type in a params file (ROS 2 cannot declare it); '
               'leave the key out or give values')
"""Why a key given ``[]`` or ``{}`` stops a node that declares its overrides: rcl reads either
as no value (NOT_SET), which rclpy refuses to declare."""


def setup_error_text(error: BaseException, name: str, argv: Sequence[str]) -> str:
    """The text of a setup error: the runtime's own, except for the declaration of a NOT_SET
    override (rclpy's "Cannot declare a statically typed parameter with default value of type
    PARAMETER_NOT_SET"), which names no cause: ``<key>: <EMPTY_VALUE>``, the key from the
    message or else the first key of node ``name`` that the command line gives no value."""
    text = str(error)
    if 'PARAMETER_NOT_SET' not in text:
        return text
    match = re.search(r"\('([^']*)'\)", text)
    key = match.group(1) if match else _first_unset(name, argv)
    return f'{key}: {EMPTY_VALUE}' if key else text


def _first_unset(name: str, argv: Sequence[str]) -> str | None:
    """The first parameter of node ``name`` (remapped as ``argv`` says) with no value."""
    from rcbf_ros.parameters.arguments import parameter_overrides, parse_ros_arguments
    try:
        arguments = parse_ros_arguments(argv)
    except ValueError:
        return None
    namespace = (arguments.namespace or '/').rstrip('/')
    values = parameter_overrides([arguments], f'{namespace}/{arguments.node_name or name}')
    return next((key for key, value in values.items() if value is None), None)


def _run(name: str, make_node: Callable[[], Any], *, run: Callable[[Any], None] | None,
         on_exit: Callable[[Any], None] | None, setup_errors: tuple[type[BaseException], ...],
         setup_message: str, shutdown_errors: tuple[type[BaseException], ...],
         rclpy: Any, argv: Sequence[str] = (),
         built: Callable[[Any], None] | None = None) -> int:
    node = None
    try:
        node = make_node()
        guard_sim_clock(node)
        if built is not None:  # after ``node`` is set: a signal meanwhile still runs on_exit
            built(node)
        (run or spin)(node)
    except (KeyboardInterrupt, *shutdown_errors):
        pass
    except setup_errors as exc:
        if node is not None:
            raise
        console_line(f'{name}: {setup_message}{setup_error_text(exc, name, argv)}')
        return 2
    except ArithmeticError as exc:
        if node is not None:
            raise
        console_line(f'{name}: {setup_message}{arithmetic_error_line(exc)}')
        return 2
    finally:
        _STOP.ignoring = True  # from here on the node stops: nothing may cut that short
        if node is not None:
            if on_exit is not None:
                on_exit(node)
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def guard_sim_clock(node: Any) -> None:
    """On rclpy, check each ``/clock`` message before the node's time source takes it
    (:class:`ClockGuard`): rclpy's raises on negative seconds, which would end the spin. Our
    runtime's time source checks them itself."""
    source = getattr(node, '_time_source', None)
    take_clock = getattr(source, 'clock_callback', None)
    if take_clock is None:  # our runtime, or an rclpy without this time source
        return
    guard = ClockGuard()

    def clock_callback(message: Any) -> None:
        take, line = guard.check(message.clock.sec, message.clock.nanosec,
                                 now_ns=time.monotonic_ns())
        if line:
            node.get_logger().warning(line)
        if take:
            take_clock(message)

    source.clock_callback = clock_callback  # the subscription use_sim_time makes later
    subscription = getattr(source, '_clock_sub', None)
    if subscription is not None:  # made while the node was built (use_sim_time true)
        subscription.callback = clock_callback


def _exit_interrupted(signum: int, frame: Any) -> None:
    """SIGINT while a node module imports: leave at once (see the module doc)."""
    os._exit(INTERRUPTED_EXIT)


def run_module(argv: Sequence[str]) -> int:
    """Import node module ``argv[0]`` and return its ``main()``, with ``sys.argv = argv``
    (its ``--help`` from :data:`LIGHT_INTERFACES`'s module, when it has one, without it).

    Returns:
        The node's exit status; :data:`INTERRUPTED_EXIT` after a SIGINT before the node
        installed its own handlers (during the import the process exits at once).
    """
    if not argv:
        console_line('usage: python -m rcbf_ros.ros.node_main <module> [args ...]')
        return 2
    sys.argv = list(argv)
    interface = _light_interface(argv[0], argv)
    if interface is not None:
        return print_help(interface, argv)
    previous = signal.signal(signal.SIGINT, _exit_interrupted)
    try:
        module = importlib.import_module(argv[0])
    except KeyboardInterrupt:
        return INTERRUPTED_EXIT
    finally:
        signal.signal(signal.SIGINT, previous)
    try:
        return module.main()
    except KeyboardInterrupt:  # before rclpy.init installed the node's handlers
        return INTERRUPTED_EXIT


if __name__ == '__main__':
    sys.exit(run_module(sys.argv[1:]))
