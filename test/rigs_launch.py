"""A model of `ros2 launch` that runs the launch files without importing launch (not
installable here).

`ros2_launch()` runs a file on stand-ins for the launch classes it uses, with launch's own rules
for launch configurations (below): every executable a run starts is looked up in the workspace
(setup.py console scripts, EXECUTABLES) and in install/ (what `ros2 launch` would run:
check_installed), every params file in CONFIG_DIR and install/; it returns which processes start
with which params files.
"""

import contextlib
import sys
import types

from rosharness import INSTALL, ROOT
import yaml

LAUNCH_DIR = ROOT / 'src' / 'stepper_drivers' / 'launch'
CONFIG_DIR = ROOT / 'config'


def console_scripts(package: str) -> set[str]:
    """Executables of a package: the console_scripts its setup.py gives setuptools (run with a
    stand-in `setup`; setup.py reads the vendor table itself)."""
    import runpy

    import setuptools
    captured = {}
    saved = setuptools.setup
    setuptools.setup = lambda **kwargs: captured.update(kwargs)
    try:
        runpy.run_path(str(ROOT / 'src' / package / 'setup.py'))
    finally:
        setuptools.setup = saved
    return {line.split('=')[0].strip()
            for line in captured['entry_points']['console_scripts']}


EXECUTABLES = {p: console_scripts(p) for p in ('stepper_drivers', 'stepper_sim')}


def node_key(yaml_name: str) -> str:
    return next(iter(yaml.safe_load((CONFIG_DIR / yaml_name).read_text())))


# Stand-ins for the launch classes the files use. They follow ros2/launch (jazzy) where the result
# depends on it, the launch configurations:
#  - entities are visited depth-first, in order (utilities/visit_all_entities_and_collect_futures),
#    and an action's condition is evaluated when it is visited (Action.visit);
#  - IncludeLaunchDescription.execute returns SetLaunchConfiguration(name, value) for each launch
#    argument, then the included description: the arguments land in the current scope;
#  - DeclareLaunchArgument.execute sets its default only when the name is not set yet;
#  - GroupAction(scoped=True) runs its actions between PushLaunchConfigurations (the current
#    values stay visible with forwarding=True, the default; ResetLaunchConfigurations clears them
#    with forwarding=False) and PopLaunchConfigurations, which restores the values of before;
#  - `ros2 launch <pkg> <file> a:=b` runs the file as IncludeLaunchDescription(file,
#    launch_arguments=[(a, b)]) (ros2launch/api/api.py, launch_a_launch_file).
# A launch class the model lacks fails the launch file's import: add it here, with its semantics.

SHARE, PREFIX = '/stand-in/share', '/stand-in/prefix'
LAUNCH_SHARE = f'{SHARE}/stepper_drivers/launch/'
CONFIG_SHARE = f'{SHARE}/stepper_drivers/config/'


class Run:
    """One `ros2 launch`: the launch configurations, their scope stack, the processes started."""

    def __init__(self, sources: dict[str, str]):
        self.configurations: dict[str, str] = {}
        self.stack: list[dict[str, str]] = []
        self.started: list[dict] = []
        self.sources = sources          # launch file name -> text, instead of the one in launch/

    def perform(self, value) -> str:
        if isinstance(value, str):
            return value
        if isinstance(value, LaunchConfiguration):
            return value.perform(self)
        if isinstance(value, (list, tuple)):
            return ''.join(self.perform(v) for v in value)
        raise AssertionError(f'the launch model cannot evaluate {value!r}')

    def visit(self, entity) -> None:
        for sub in entity.visit(self) or ():
            self.visit(sub)


class LaunchDescription:
    def __init__(self, initial_entities=()):
        self.entities = list(initial_entities)

    def visit(self, run: Run):
        return self.entities


class LaunchConfiguration:
    def __init__(self, variable_name, *, default=None):
        self.name, self.default = variable_name, default

    def perform(self, run: Run) -> str:
        if self.name in run.configurations:
            return run.configurations[self.name]
        assert self.default is not None, f'launch configuration {self.name!r} is not set'
        return run.perform(self.default)


class IfCondition:
    def __init__(self, predicate_expression):
        self.expression = predicate_expression

    def evaluate(self, run: Run) -> bool:
        value = run.perform(self.expression).strip().lower()
        # launch.conditions.evaluate_condition_expression
        assert value in ('true', 'false', '1', '0'), f'condition {value!r} is not true or false'
        return value in ('true', '1')


class UnlessCondition(IfCondition):
    def evaluate(self, run: Run) -> bool:
        return not super().evaluate(run)


class Action:
    def __init__(self, *, condition=None, **_options):     # output, description, ...
        self.condition = condition

    def visit(self, run: Run):
        if self.condition is None or self.condition.evaluate(run):
            return self.execute(run)
        return None

    def execute(self, run: Run):
        return None


class SetLaunchConfiguration(Action):
    def __init__(self, name, value, **options):
        super().__init__(**options)
        self.name, self.value = name, value

    def execute(self, run: Run):
        run.configurations[run.perform(self.name)] = run.perform(self.value)


class DeclareLaunchArgument(Action):
    def __init__(self, name, *, default_value=None, choices=None, **options):
        super().__init__(**options)
        self.name, self.default_value, self.choices = name, default_value, choices

    def execute(self, run: Run):
        if self.name not in run.configurations:
            assert self.default_value is not None, f'launch argument {self.name} not provided'
            run.configurations[self.name] = run.perform(self.default_value)
        if self.choices is not None:
            assert run.configurations[self.name] in self.choices, self.name


class PushLaunchConfigurations(Action):
    def execute(self, run: Run):
        run.stack.append(dict(run.configurations))


class PopLaunchConfigurations(Action):
    def execute(self, run: Run):
        run.configurations = run.stack.pop()


class ResetLaunchConfigurations(Action):
    def __init__(self, launch_configurations, **options):
        super().__init__(**options)
        self.launch_configurations = launch_configurations

    def execute(self, run: Run):
        kept = {run.perform(k): run.perform(v) for k, v in self.launch_configurations.items()}
        run.configurations.clear()
        run.configurations.update(kept)


class GroupAction(Action):
    def __init__(self, actions, *, scoped=True, forwarding=True, launch_configurations=None,
                 **options):
        super().__init__(**options)
        self.actions, self.scoped, self.forwarding = list(actions), scoped, forwarding
        self.launch_configurations = launch_configurations or {}

    def execute(self, run: Run):
        sets = [SetLaunchConfiguration(k, v) for k, v in self.launch_configurations.items()]
        if not self.scoped:
            return [*sets, *self.actions]
        if not self.forwarding:
            sets = [ResetLaunchConfigurations(self.launch_configurations)]
        return [PushLaunchConfigurations(), *sets, *self.actions, PopLaunchConfigurations()]


class PythonLaunchDescriptionSource:
    def __init__(self, launch_file_path):
        self.path = launch_file_path

    def load(self, run: Run) -> LaunchDescription:
        path = run.perform(self.path)
        assert path.startswith(LAUNCH_SHARE), f'{path}: not a launch file of stepper_drivers'
        name = path[len(LAUNCH_SHARE):]
        text = run.sources.get(name) or (LAUNCH_DIR / name).read_text()
        scope = {'__name__': name.replace('.', '_'), '__file__': path}
        exec(compile(text, name, 'exec'), scope)
        return scope['generate_launch_description']()


class OpaqueFunction(Action):
    # launch.actions.OpaqueFunction: function(context, *args, **kwargs) -> actions or None; the
    # model's Run is the context (LaunchConfiguration.perform takes it)
    def __init__(self, *, function, args=None, kwargs=None, **options):
        super().__init__(**options)
        self.function, self.args, self.kwargs = function, args or [], kwargs or {}

    def execute(self, run: Run):
        return self.function(run, *self.args, **self.kwargs)


class IncludeLaunchDescription(Action):
    def __init__(self, launch_description_source, *, launch_arguments=None, **options):
        super().__init__(**options)
        self.source = launch_description_source
        self.launch_arguments = tuple(launch_arguments or ())

    def execute(self, run: Run):
        description = self.source.load(run)
        return [*(SetLaunchConfiguration(k, v) for k, v in self.launch_arguments), description]


class Node(Action):
    def __init__(self, *, executable, package=None, name=None, parameters=None, **options):
        super().__init__(**options)
        self.package, self.executable, self.node_name = package, executable, name
        self.parameters = parameters or []

    def execute(self, run: Run):
        if self.package is not None:          # else from PATH (the model's own tests)
            check_installed(self.package, self.executable)
        run.started.append({'executable': self.executable, 'name': self.node_name,
                            'parameters': [run.perform(p) for p in self.parameters]})


class LifecycleNode(Node):
    # launch_ros.actions.LifecycleNode (Jazzy): name and namespace are required keywords
    def __init__(self, *, name, namespace, **options):
        super().__init__(name=name, **options)
        self.namespace = namespace


class ExecuteProcess(Action):
    def __init__(self, *, cmd, **options):
        super().__init__(**options)
        self.cmd = cmd

    def execute(self, run: Run):
        cmd = [run.perform(c) for c in self.cmd]
        # os.path.join(get_package_prefix('pkg'), 'lib', 'pkg', 'exe')
        assert cmd[0].startswith(PREFIX + '/'), f'{cmd[0]}: not an executable of a package'
        package, lib, package_again, exe = cmd[0][len(PREFIX) + 1:].split('/')
        assert (lib, package_again) == ('lib', package), cmd[0]
        check_installed(package, exe)
        run.started.append({'executable': cmd[0].rsplit('/', 1)[-1], 'cmd': cmd[1:]})


def check_installed(package: str, executable: str) -> None:
    assert executable in EXECUTABLES[package], f'{package} has no executable {executable}'
    assert (INSTALL / package / 'lib' / package / executable).exists(), \
        f'{executable} not installed (run scripts/bootstrap.sh)'


def get_package_share_directory(package_name: str) -> str:
    return f'{SHARE}/{package_name}'


def get_package_prefix(package_name: str) -> str:
    return f'{PREFIX}/{package_name}'


def _module(name: str, *members) -> types.ModuleType:
    module = types.ModuleType(name)
    for m in members:
        setattr(module, m.__name__, m)
    return module


STAND_INS = {
    'launch': _module('launch', LaunchDescription),
    'launch.actions': _module('launch.actions', DeclareLaunchArgument, ExecuteProcess, GroupAction,
                              IncludeLaunchDescription, OpaqueFunction, SetLaunchConfiguration),
    'launch.conditions': _module('launch.conditions', IfCondition, UnlessCondition),
    'launch.substitutions': _module('launch.substitutions', LaunchConfiguration),
    'launch.launch_description_sources': _module('launch.launch_description_sources',
                                                 PythonLaunchDescriptionSource),
    'launch_ros': _module('launch_ros'),
    'launch_ros.actions': _module('launch_ros.actions', Node, LifecycleNode),
    'ament_index_python': _module('ament_index_python'),
    'ament_index_python.packages': _module('ament_index_python.packages',
                                           get_package_share_directory, get_package_prefix),
}


@contextlib.contextmanager
def stand_ins():
    saved = {name: sys.modules.get(name) for name in STAND_INS}
    sys.modules.update(STAND_INS)
    try:
        yield
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name)
            else:
                sys.modules[name] = module


def ros2_launch(launch_file: str, sources: dict[str, str] | None = None,
                **arguments: str) -> dict[str, list[str]]:
    """`ros2 launch stepper_drivers <launch_file> name:=value...`: what it starts, as
    {executable: params files (config/ files as 'config/<name>') or command-line arguments}."""
    run = Run(sources or {})
    with stand_ins():
        run.visit(LaunchDescription([IncludeLaunchDescription(
            PythonLaunchDescriptionSource(LAUNCH_SHARE + launch_file),
            launch_arguments=arguments.items())]))
    started = {}
    for p in run.started:
        assert p['executable'] not in started, f'{p["executable"]} started twice'
        if 'cmd' in p:
            started[p['executable']] = p['cmd']
            continue
        files = [f.replace(CONFIG_SHARE, 'config/') for f in p['parameters']]
        for f in files:
            if f.startswith('config/'):
                name = f.removeprefix('config/')
                assert (CONFIG_DIR / name).exists(), f'{f} missing'
                assert (INSTALL / 'stepper_drivers' / 'share' / 'stepper_drivers' / 'config' /
                        name).exists(), f'{f} not installed (run scripts/bootstrap.sh)'
                configured = node_key(name)
                assert configured == p['name'], \
                    f'{p["name"]} started with {f}, which configures {configured}'
        started[p['executable']] = files
    return started
