"""package.xml declares a rosdep key for every third-party import (rosdep_keys.yaml maps them)."""
import ast
import re
import sys
from xml.etree import ElementTree
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent


def third_party_imports() -> dict[str, str]:
    """Top-level name of every absolute import in exit_decision/ and launch/ that is neither
    the standard library nor this package -> a file importing it."""
    found = {}
    for path in sorted([*(REPO / 'exit_decision').rglob('*.py'), *(REPO / 'launch').glob('*.py')]):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                modules = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                modules = [node.module]
            else:
                continue
            for module in modules:
                top = module.split('.')[0]
                if top not in sys.stdlib_module_names and top != 'exit_decision':
                    found.setdefault(top, path.relative_to(REPO).as_posix())
    return found


def declared_keys(tag: str = '') -> set[str]:
    """The rosdep keys package.xml declares in its ``tag`` elements (e.g. exec_depend; empty:
    every kind of *depend)."""
    root = ElementTree.parse(REPO / 'package.xml').getroot()
    return {element.text for element in root if element.tag == tag or (not tag and element.tag.endswith('depend'))}


def test_every_import_is_mapped_to_a_declared_rosdep_key():
    table = yaml.safe_load((REPO / 'rosdep_keys.yaml').read_text())
    keys, through_messages = table['imports'], set(table['through_messages'])
    declared = declared_keys('exec_depend')
    imports = third_party_imports()
    unmapped = {name: path for name, path in imports.items() if name not in keys}
    assert not unmapped, f'imports without a rosdep key in rosdep_keys.yaml: {unmapped}'
    missing = {keys[name] for name in imports} - declared
    assert not missing, f'rosdep keys not declared in package.xml: {sorted(missing)}'
    assert declared == set(keys.values()) | through_messages, 'package.xml declares exactly the mapped keys'
    assert set(keys) == set(imports), f'mapped but never imported: {sorted(set(keys) - set(imports))}'


def declared_pip_keys() -> dict[str, str]:
    """Each rosdep pip key package.xml declares (python3-<name>-pip) -> <name>."""
    return {key: match.group(1) for key in declared_keys() if (match := re.fullmatch(r'python3-(.+)-pip', key))}


def test_rosdep_yaml_defines_every_pip_key_for_a_pinned_distribution():
    """rosdep.yaml (the rosdep source the README registers) defines exactly the python3-<name>-pip
    keys package.xml declares, each <name> pinned in requirements.txt; test_install_colcon.py
    asks rosdep itself what they resolve to."""
    pip_keys = declared_pip_keys()
    assert set(yaml.safe_load((REPO / 'rosdep.yaml').read_text())) == set(pip_keys)
    pinned = {line.split('==')[0].split('[')[0].strip().lower() for line in
              (REPO / 'requirements.txt').read_text().splitlines() if '==' in line and not line.startswith('#')}
    assert set(pip_keys.values()) <= pinned, f'not pinned in requirements.txt: {set(pip_keys.values()) - pinned}'
