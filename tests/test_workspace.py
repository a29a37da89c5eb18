"""The workspace: messages round-trip, packages are indexed, layers stay apart."""
import ast
import importlib
import pathlib
import re

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from conftest import ROOT

msg = pytest.importorskip('mshoot_msgs.msg')
PACKAGES = ('mshoot_core', 'mshoot_nodes', 'mshoot_msgs', 'mshoot_studies', 'mshoot_testing')
#: What ships; test support lives in mshoot_testing.
PRODUCTION = ('mshoot_core', 'mshoot_nodes', 'mshoot_msgs', 'mshoot_studies')
SRC = ROOT / 'ros2_ws' / 'src'


def _filled(msg_type):
    """Return an instance of ``msg_type`` with every field set to a distinct value."""
    m = msg_type()
    m.header.stamp.sec = 7200
    m.header.stamp.nanosec = 5
    m.header.frame_id = 'zone_a'
    rng = np.random.default_rng(abs(hash(msg_type.__name__)) % 1000)
    for name, kind in m.get_fields_and_field_types().items():
        if name == 'header':
            continue
        if kind == 'double':
            setattr(m, name, float(rng.normal()))
        elif kind == 'sequence<double>':
            setattr(m, name, rng.normal(size=5).tolist())
        elif kind == 'sequence<string>':
            setattr(m, name, [f'{name}_{k} ✓' for k in range(3)])
        elif kind == 'boolean':
            setattr(m, name, True)
        elif kind == 'sequence<boolean>':
            setattr(m, name, [True, False, True])
        elif kind in ('int32', 'uint32'):
            setattr(m, name, int(rng.integers(1, 1000)))
        elif kind == 'string':
            setattr(m, name, 'solver: converged ✓')
        else:
            raise AssertionError(f'unhandled field type {kind} of {msg_type.__name__}.{name}')
    return m


@pytest.mark.parametrize('name', ['ZoneState', 'Disturbances', 'Forecast', 'Setpoint',
                                  'MpcStatus'])
def test_message_round_trip(name):
    msg_type = getattr(msg, name)
    original = _filled(msg_type)
    back = deserialize_message(serialize_message(original), msg_type)
    assert back == original
    for field in original.get_fields_and_field_types():
        assert np.all(np.asarray(getattr(back, field)) == np.asarray(getattr(original, field))) \
            if field != 'header' else back.header == original.header


def test_contract_field_names():
    """The field names are a contract with tools outside the project."""
    expected = {
        'ZoneState': {'header', 'state_names', 'state_values', 'output_names', 'output_values',
                      'control_names', 'control_values'},
        'Disturbances': {'header', 'names', 'values'},
        'Forecast': {'header', 'step_s', 'series_names', 'series_values', 'comfort_min_c',
                     'comfort_max_c', 'price_per_kwh'},
        'Setpoint': {'header', 'step_s', 'control_names', 'control_values', 'temperature_names',
                     'temperature_setpoints_c', 'plan_controls', 'plan_temperatures_c'},
        'MpcStatus': {'header', 'success', 'fallback', 'message', 'iterations',
                      'solve_time_s', 'objective', 'max_defect'},
    }
    for name, fields in expected.items():
        have = set(getattr(msg, name).get_fields_and_field_types())
        assert fields <= have, f'{name} lacks {fields - have}'


def test_ament_index_knows_the_packages():
    from ament_index_python.packages import get_package_prefix, get_packages_with_prefixes
    known = get_packages_with_prefixes()
    for pkg in PACKAGES:
        assert pkg in known, f'{pkg} not in the ament index'
        assert pathlib.Path(get_package_prefix(pkg)).is_dir()


@pytest.mark.parametrize('exe', ['emulator', 'forecaster', 'mpc'])
def test_executables_installed_for_ros2_run(exe):
    from ament_index_python.packages import get_package_prefix
    path = pathlib.Path(get_package_prefix('mshoot_nodes')) / 'lib' / 'mshoot_nodes' / exe
    assert path.is_file(), f'{path} missing: `ros2 run mshoot_nodes {exe}` would fail'
    assert path.stat().st_mode & 0o111


#: Top-level modules mshoot_core may never import: ROS client libraries, interfaces, bags,
#: launch, and the packages above it.
FORBIDDEN_IN_CORE = re.compile(r'^(rclpy|rcl\w*|rosbags|rosbag2\w*|rosidl\w*|ament\w*|launch\w*|'
                               r'\w+_msgs|\w+_srvs|mshoot_nodes|mshoot_studies|mshoot_testing)$')


def imported_modules(source: str) -> list[tuple[int, str]]:
    """
    Return every module a Python source imports, in every form.

    The forms: ``import a.b``, ``from a import b``, and ``importlib.import_module('a')`` /
    ``__import__('a')`` with a literal name.
    """
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant) \
                and isinstance(node.args[0].value, str):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, 'id', '')
            if name in ('import_module', '__import__'):
                found.append((node.lineno, node.args[0].value))
    return found


def test_import_guard_sees_every_form():
    source = ('import rclpy.node\nfrom std_msgs.msg import String\nimport numpy as np\n'
              'def f():\n    from rosbags.rosbag2 import Reader\n'
              'importlib.import_module("launch")\n__import__("mshoot_nodes.bringup")\n'
              'from . import sibling\n')
    modules = [name for _, name in imported_modules(source)]
    assert modules == ['rclpy.node', 'std_msgs.msg', 'numpy', 'rosbags.rosbag2', 'launch',
                       'mshoot_nodes.bringup']
    assert [m for m in modules if FORBIDDEN_IN_CORE.match(m.split('.')[0])] == [
        'rclpy.node', 'std_msgs.msg', 'rosbags.rosbag2', 'launch', 'mshoot_nodes.bringup']


def test_core_never_imports_ros():
    core = SRC / 'mshoot_core'
    offenders = [f'{p.relative_to(core)}:{line} {name}' for p in sorted(core.rglob('*.py'))
                 for line, name in imported_modules(p.read_text())
                 if FORBIDDEN_IN_CORE.match(name.split('.')[0])]
    assert not offenders, f'mshoot_core must not depend on ROS or the packages above it: ' \
                          f'{offenders}'
    depends = re.findall(r'<(?:\w+_)?depend>([^<]+)<', (core / 'package.xml').read_text())
    assert not [d for d in depends if FORBIDDEN_IN_CORE.match(d)], depends


def test_test_doubles_live_outside_the_production_packages():
    """Fault injection and the test harness are in mshoot_testing, which nothing ships."""
    src = ROOT / 'ros2_ws' / 'src'
    testing = {p.stem for p in (src / 'mshoot_testing' / 'mshoot_testing').glob('*.py')}
    assert {'faults', 'harness'} <= testing
    for package in PRODUCTION:
        files = [p for p in (src / package).rglob('*')
                 if p.is_file() and p.suffix in ('.py', '.xml')]
        assert not [p for p in files if p.stem in ('faults', 'harness')], package
        offenders = [str(p) for p in files if 'mshoot_testing' in p.read_text(errors='replace')]
        assert not offenders, f'{package} must not depend on the test support: {offenders}'


def _python_sources(package: str) -> list[pathlib.Path]:
    return sorted((SRC / package / package).rglob('*.py'))


def test_applications_live_outside_the_library():
    """
    The core holds models, shooting, MPC, emulation and KPIs; applications are elsewhere.

    The case, the study, its sweeps and Setup 2 are applications in mshoot_studies.
    """
    applications = {'case', 'study', 'study_plots', 'study_runs', 'sweeps', 'setup2', 'cli'}
    core_modules = {p.stem for p in _python_sources('mshoot_core')}
    assert not core_modules & applications, sorted(core_modules & applications)
    assert {'case', 'study', 'study_plots', 'sweeps', 'setup2', 'cli'} <= {
        p.stem for p in _python_sources('mshoot_studies')}
    for name in ('case', 'study', 'study_plots', 'study_runs'):
        with pytest.raises(ModuleNotFoundError):
            importlib.import_module(f'mshoot_core.{name}')
    assert 'train_setup2' not in (SRC / 'mshoot_core' / 'mshoot_core' / 'models' /
                                  'sklearn_model.py').read_text()


@pytest.mark.parametrize('package', ['mshoot_core', 'mshoot_nodes'])
def test_library_and_nodes_import_no_application(package):
    """
    Nodes and the core library import no command-line module (nothing of mshoot_studies).

    Except the BOPTEST benchmark's runner over ROS (``make boptest``), itself a command: it
    tunes the rule and writes the report with the applications' code.
    """
    pattern = re.compile(r'^\s*(from|import)\s+mshoot_studies\b', re.MULTILINE)
    runners = {'boptest_run.py'}
    offenders = [str(p) for p in _python_sources(package)
                 if p.name not in runners and pattern.search(p.read_text())]
    assert not offenders, offenders


def test_applications_never_import_ros():
    pattern = re.compile(r'import rclpy|_msgs|rosbags|^\s*(from|import) launch', re.MULTILINE)
    offenders = [str(p) for p in (SRC / 'mshoot_studies').rglob('*')
                 if p.is_file() and p.suffix in ('.py', '.xml', '.cfg')
                 and pattern.search(p.read_text(errors='replace'))]
    assert not offenders, offenders
