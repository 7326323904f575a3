"""The package's shape (docs/architecture.md). The import direction: every import statement
of every module, at any depth (imports inside functions included), read with ``ast``.

- ``LAYERS``: the package's folders and root modules from lowest to highest; a module imports
  only from its own folder (or module) and from lower layers, never from its own layer's
  others or a higher one: inference (``model/``) does not depend on training, training may use
  evaluation's runs, nothing of the core imports ``ros/`` or the command line;
- no module outside ``ros/`` imports rclpy, launch or a ROS message package;
- ``model/`` writes no checkpoints (training does, ``learning/checkpoints``);
- docs/architecture.md lists every module, in the layers' order.

And the size: no module over 600 lines, each with a docstring saying its job.
"""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / 'exit_decision'
ROS_PACKAGES = {'rclpy', 'launch', 'launch_ros', 'rcl_interfaces', 'diagnostic_msgs', 'visualization_msgs',
                'std_msgs', 'builtin_interfaces', 'geometry_msgs', 'rosgraph_msgs', 'exit_decision_msgs',
                'composition_interfaces', 'ament_index_python'}


#: lowest first; a unit (a folder, or a module at the package root) imports only lower layers
LAYERS = (
    ('errors', 'config', 'tables'),
    ('traffic',),
    ('scenario', 'actions', 'graph', 'reward', 'input_checks'),
    ('step_gaps', 'episode_log', 'encoders', 'agents'),
    ('shield_overrides', 'model'),
    ('env', 'visualization'),
    ('ecosystem', 'driving'),
    ('evaluation',),
    ('learning',),
    ('experiments',),
    ('benchmarks',),
    ('ros',),
    ('cli',),
    ('__main__', '__init__'),
)
LAYER_OF = {unit: index for index, units in enumerate(LAYERS) for unit in units}


def unit_of(name: str) -> str | None:
    """The layer unit of a dotted module name (``exit_decision.model.policy`` -> ``model``);
    None for the package itself."""
    parts = name.split('.')
    return parts[1] if len(parts) > 1 and parts[0] == 'exit_decision' else None


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
    own = unit_of(module) or '__init__'
    in_ros = own == 'ros'
    for name in sorted(names):
        other = unit_of(name)
        if other is not None and other != own and LAYER_OF[other] >= LAYER_OF[own]:
            found.append(f'{own} (layer {LAYER_OF[own]}) -> {name} (layer {LAYER_OF[other]})')
        if not in_ros and name.split('.')[0] in ROS_PACKAGES - {'ament_index_python'}:
            found.append(f'ROS outside ros/: {name}')
    return found


def test_every_unit_of_the_package_has_a_layer():
    units = {unit_of(module) or '__init__' for module, _ in modules()}
    assert units <= set(LAYER_OF), f'not in LAYERS: {sorted(units - set(LAYER_OF))}'
    assert len(LAYER_OF) == sum(len(units) for units in LAYERS), 'a unit is in two layers'


#: the modules that step the environment: itself, its PettingZoo wrapper, the one episode loop,
#: and the ROS bridge (the simulation behind ROS topics, stepped as commands arrive)
STEPPING = {'exit_decision.env', 'exit_decision.ecosystem', 'exit_decision.driving.episode',
            'exit_decision.ros.nodes.sumo_bridge'}


def steps_an_environment(path: Path) -> bool:
    """Does the file call ``<...env>.step``, ``.step_commands`` or ``.simulate_step``?"""
    for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in (
                'step', 'step_commands', 'simulate_step'):
            owner = node.func.value
            name = owner.attr if isinstance(owner, ast.Attribute) else getattr(owner, 'id', '')
            if name.endswith('env'):
                return True
    return False


def test_one_function_outside_the_environment_steps_it():
    stepping = {module for module, path in modules() if steps_an_environment(path)}
    assert stepping <= STEPPING, f'these step the environment themselves: {sorted(stepping - STEPPING)}; ' \
                                 f'play the episode with driving.episode.play_episode'


def test_model_writes_no_checkpoints():
    for path in (PACKAGE / 'model').rglob('*.py'):
        assert 'torch.save' not in path.read_text(encoding='utf-8'), f'{path}: checkpoints are written by learning/'


def test_the_architecture_page_lists_every_module_in_the_layers_order():
    text = (PACKAGE.parent / 'docs' / 'architecture.md').read_text(encoding='utf-8')
    positions = {}
    for module, path in modules():
        name = str(path.relative_to(PACKAGE.parent))
        if path.name == '__init__.py' and not _has_code(path):
            continue
        assert f'`{name}`' in text, f'docs/architecture.md does not list {name}'
        positions[name] = (text.index(f'`{name}`'), LAYER_OF[unit_of(module) or '__init__'])
    by_place = [layer for _, layer in sorted(positions.values())]
    assert by_place == sorted(by_place), 'docs/architecture.md lists the modules out of the layers\' order'


def _has_code(path: Path) -> bool:
    """A module with more than its docstring (a package's ``__init__`` that only says what it holds has none)."""
    body = ast.parse(path.read_text(encoding='utf-8')).body
    return any(not (isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)) for node in body)


@pytest.mark.parametrize('module, path', list(modules()), ids=[m for m, _ in modules()])
def test_imports_follow_the_direction(module, path):
    assert not violations(module, imported(path)), f'{path}: ' + '; '.join(violations(module, imported(path)))


def test_the_rules_catch_what_they_forbid(tmp_path):
    assert violations('exit_decision.env', {'exit_decision.ros.topics'}) == [
        'env (layer 5) -> exit_decision.ros.topics (layer 11)']
    assert violations('exit_decision.model.policy', {'exit_decision.learning.trainer'})
    assert violations('exit_decision.model.policy', {'exit_decision.shield_overrides'}), 'the same layer: not allowed'
    assert violations('exit_decision.evaluation.evaluate', {'exit_decision.learning.validation'})
    assert not violations('exit_decision.learning.validation', {'exit_decision.evaluation.evaluate'})
    assert not violations('exit_decision.model.policy', {'exit_decision.model.networks'}), 'within its own folder'
    assert violations('exit_decision.ros.nodes.decision_node', {'exit_decision.cli.arguments'})
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
