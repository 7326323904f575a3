"""The package's shape (docs/architecture.md). The import direction: every import statement
of every module, at any depth (imports inside functions included), read with ``ast``.

- the core (every module outside ``ros/`` and the command line) never imports ``ros/``;
- ``model/`` (networks, policy, names, modes) imports nothing from ``learning/``,
  ``experiments/`` or ``ros/``: inference does not depend on training;
- nothing imports the command line (``cli/``) but ``__main__`` and the command line itself;
- no module outside ``ros/`` imports rclpy, launch or a ROS message package.

And the size: no module over 600 lines, each with a docstring saying its job.
"""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / 'exit_decision'
ROS_PACKAGES = {'rclpy', 'launch', 'launch_ros', 'rcl_interfaces', 'diagnostic_msgs', 'visualization_msgs',
                'std_msgs', 'builtin_interfaces', 'geometry_msgs', 'rosgraph_msgs', 'exit_decision_msgs',
                'composition_interfaces', 'ament_index_python'}


def modules():
    """(dotted name, path) of every module of the package."""
    for path in sorted(PACKAGE.rglob('*.py')):
        parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
        yield '.'.join(parts[:-1] if parts[-1] == '__init__' else parts), path


def imported(path: Path) -> set[str]:
    """Every module name an import statement of the file names, at any depth."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'), str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                raise AssertionError(f'{path}: relative import (the rules read absolute names)')
            names.add(node.module)
            names |= {f'{node.module}.{alias.name}' for alias in node.names}
    return names


def within(name: str, package: str) -> bool:
    return name == package or name.startswith(package + '.')


def violations(module: str, names: set[str]) -> list[str]:
    found = []
    in_ros = within(module, 'exit_decision.ros')
    is_cli = within(module, 'exit_decision.cli') or module == 'exit_decision.__main__'
    for name in sorted(names):
        if not in_ros and not is_cli and within(name, 'exit_decision.ros'):
            found.append(f'core -> ros: {name}')
        if within(module, 'exit_decision.model') and any(
                within(name, f'exit_decision.{floor}') for floor in ('learning', 'experiments', 'ros')):
            found.append(f'model -> {name}')
        if within(name, 'exit_decision.cli') and not is_cli:
            found.append(f'-> cli: {name}')
        if not in_ros and name.split('.')[0] in ROS_PACKAGES - {'ament_index_python'}:
            found.append(f'ROS outside ros/: {name}')
    return found


@pytest.mark.parametrize('module, path', list(modules()), ids=[m for m, _ in modules()])
def test_imports_follow_the_direction(module, path):
    assert not violations(module, imported(path)), f'{path}: ' + '; '.join(violations(module, imported(path)))


def test_the_rules_catch_what_they_forbid(tmp_path):
    assert violations('exit_decision.env', {'exit_decision.ros.topics'}) == ['core -> ros: exit_decision.ros.topics']
    assert violations('exit_decision.model.policy', {'exit_decision.learning.trainer'})
    assert violations('exit_decision.learning.trainer', {'exit_decision.cli'})
    assert violations('exit_decision.evaluation.report', {'exit_decision.cli.arguments'})
    assert not violations('exit_decision.cli.stack', {'exit_decision.cli.arguments', 'exit_decision.ros.stack.realtime'})
    assert violations('exit_decision.benchmarks', {'rclpy.node'})
    assert not violations('exit_decision.ros.nodes.decision_node', {'rclpy.node', 'exit_decision.model.policy'})
    assert not violations('exit_decision.learning.trainer', {'exit_decision.model.networks'})
    nested = tmp_path / 'nested.py'
    nested.write_text('def f():\n    if True:\n        from exit_decision.ros import topics\n')
    assert 'exit_decision.ros.topics' in imported(nested), 'an import inside a function is read too'


MAX_LINES = 600


@pytest.mark.parametrize('module, path', list(modules()), ids=[m for m, _ in modules()])
def test_each_module_is_short_and_says_its_job(module, path):
    source = path.read_text(encoding='utf-8')
    lines = len(source.splitlines())
    assert lines <= MAX_LINES, f'{path}: {lines} lines (at most {MAX_LINES}): split it by job'
    assert (ast.get_docstring(ast.parse(source)) or '').strip(), f'{path}: no docstring saying what the module is for'


def test_the_decision_node_stays_thin():
    """It declares parameters and wires callbacks; choosing, loading and driving are model/'s."""
    path = PACKAGE / 'ros' / 'nodes' / 'decision_node.py'
    assert len(path.read_text(encoding='utf-8').splitlines()) < 200, f'{path}: the node is glue, under 200 lines'
