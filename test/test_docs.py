"""What the documentation tells a reader to type exists: in README.md and docs/*.md, every
``exit-decision <command> --option`` (also ``python -m exit_decision`` and ``scripts/main``,
which runs ``exit-decision stack``), every ``ros2 launch exit_decision exit_decision.launch.py
<argument>:=``, every ``ros2 param set|get|describe /<node> <parameter>`` and ``ros2 run
exit_decision <executable> --ros-args -p <parameter>:=``, in the shell blocks (```bash, ```sh,
```console, plain ```) and the inline `code` spans; every relative link points to a file or
directory of the repository; and docs/cli.md has a section for every command that names each of
its options (an options-only span there, `--episodes N`, is checked against its section's command).

The commands and options come from the parser itself (``exit_decision.cli.build_parser``), the
launch arguments from the node table the launch file declares them from, and each node's
parameters from its code (the ``declare`` calls of exit_decision/ros/nodes/ and of the helpers
in exit_decision/ros/parameters.py, read with ``ast``): no rclpy, no subprocess.
"""
from __future__ import annotations

import argparse
import ast
import functools
import itertools
import re
from dataclasses import dataclass
from pathlib import Path

from exit_decision.cli import build_parser
from exit_decision.ros.stack.node_table import ARGUMENTS, NODE_NAMES

REPO = Path(__file__).resolve().parent.parent
NODES_DIR = REPO / 'exit_decision' / 'ros' / 'nodes'
PARAMETER_HELPERS = REPO / 'exit_decision' / 'ros' / 'parameters.py'

#: fenced blocks whose lines are read as commands (the language after the fence)
SHELL_FENCES = {'', 'bash', 'sh', 'shell', 'console', 'zsh', 'shell-session'}
#: parameters every rclpy node declares itself (not in this project's code)
RCLPY_PARAMETERS = {'use_sim_time', 'start_type_description_service'}
#: what ends a command in a shell line
SEPARATORS = {';', '&&', '||', '|', 'do', 'then', '(', ')', '$('}
PLAIN = re.compile(r'^[a-z][a-z0-9_-]*$')          # a command's, node's or executable's name
OPTION = re.compile(r'^--[a-z][a-z0-9-]*')
IDENTIFIER = re.compile(r'^[A-Za-z_][\w.]*$')       # a parameter's or launch argument's name


def documents() -> list[Path]:
    return [REPO / 'README.md', *sorted((REPO / 'docs').glob('*.md'))]


def shown(path: Path) -> Path:
    return path.relative_to(REPO) if path.is_relative_to(REPO) else path


# --- reading the markdown ------------------------------------------------------------------

@dataclass(frozen=True)
class Snippet:
    line: int     # 1-based line in the file
    text: str     # a line of a shell block, or one inline code span
    fenced: bool
    # the command of the section the span is in (a heading naming `exit-decision <command>`): a
    # span that is only options (`--episodes N`) is read as that command's
    section: tuple[str, ...] = ()


FENCE = re.compile(r'^\s*(`{3,}|~{3,})\s*([\w+-]*)')
# an inline code span; it may wrap onto the next lines of its paragraph, not past a blank line
CODE_SPAN = re.compile(r'(?<!`)(`+)(?!`)((?:(?!\n[ \t]*\n).)+?)(?<!`)\1(?!`)', re.DOTALL)
HEADING = re.compile(r'^#{1,6}\s')


def _section(heading: str) -> tuple[str, ...]:
    """The command a heading names in a code span (`exit-decision bag repair BAG`: bag repair)."""
    for span in CODE_SPAN.finditer(heading):
        tokens = span.group(2).split()
        if tokens[:1] == ['exit-decision']:
            return tuple(itertools.takewhile(PLAIN.match, tokens[1:]))[:2]
    return ()


def _inline(first: int, lines: list[str], snippets: list[Snippet], prose: list[tuple[int, str]],
            section: tuple[str, ...]) -> tuple[str, ...]:
    """The code spans of ``lines`` (from line ``first`` on) as snippets; the lines without them as
    prose; returns the section command at their end (a heading starts a section)."""
    text = '\n'.join(lines)
    sections, offset = [], 0   # (offset of a heading, its command)
    for line in lines:
        if HEADING.match(line):
            sections.append((offset, _section(line)))
        offset += len(line) + 1
    for span in CODE_SPAN.finditer(text):
        section = next((command for at, command in reversed(sections) if at <= span.start()), section)
        # a table cell's code span writes | as \| (GitHub renders it as |)
        snippets.append(Snippet(first + text.count('\n', 0, span.start()),
                                span.group(2).replace('\n', ' ').replace('\\|', '|'), False, section))
    without = CODE_SPAN.sub(lambda span: '\n' * span.group(0).count('\n'), text)
    prose += list(enumerate(without.split('\n'), first))
    return sections[-1][1] if sections else section


def read_markdown(path: Path) -> tuple[list[Snippet], list[tuple[int, str]]]:
    """The file's code (shell block lines and inline spans) and its prose lines with the code
    spans taken out (for links); lines of other fenced blocks (json, python, ...) are neither."""
    snippets, prose, outside = [], [], []
    fence, shell, section = None, False, ()
    for number, line in enumerate(path.read_text(encoding='utf-8').splitlines(), 1):
        opened = FENCE.match(line)
        if fence is None and opened:
            if outside:
                section = _inline(outside[0][0], [text for _, text in outside], snippets, prose, section)
                outside = []
            fence, shell = opened.group(1), opened.group(2).lower() in SHELL_FENCES
        elif fence is not None:
            if line.strip().startswith(fence) and not line.strip().strip(fence[0]):
                fence = None
            elif shell:
                snippets.append(Snippet(number, line, True))
        else:
            outside.append((number, line))
    if outside:
        _inline(outside[0][0], [text for _, text in outside], snippets, prose, section)
    return snippets, prose


# --- the commands, parameters and launch arguments the code has --------------------------

@functools.lru_cache(maxsize=None)
def cli_parser() -> argparse.ArgumentParser:
    return build_parser()


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser] | None:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return None


def options(parser: argparse.ArgumentParser) -> set[str]:
    return {option for action in parser._actions for option in action.option_strings}


def _call_name(call: ast.Call) -> str:
    return call.func.id if isinstance(call.func, ast.Name) else getattr(call.func, 'attr', '')


def _text(node: ast.AST | None) -> str | None:
    return node.value if isinstance(node, ast.Constant) and isinstance(node.value, str) else None


#: the functions that declare one parameter, and which argument is its name
DECLARES = {'declare': 1, 'declare_parameter': 0}


def _declared(scope: ast.AST, helpers: dict[str, set[str]]) -> set[str]:
    """The parameter names ``scope`` declares: through ``declare`` / ``declare_parameter`` with a
    literal name, a helper of ``helpers``, or a local function passing its argument to one."""
    wrappers = dict(DECLARES)
    for function in ast.walk(scope):   # def p(name, ...): return declare(self, name, ...)
        if isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
            arguments = [argument.arg for argument in function.args.args]
            for call in ast.walk(function):
                if isinstance(call, ast.Call) and _call_name(call) in DECLARES:
                    given = call.args[DECLARES[_call_name(call)]:][:1]
                    if given and isinstance(given[0], ast.Name) and given[0].id in arguments:
                        wrappers.setdefault(function.name, arguments.index(given[0].id))
    names = set()
    for call in ast.walk(scope):
        if not isinstance(call, ast.Call):
            continue
        name = _call_name(call)
        if name in helpers:
            names |= helpers[name]
        elif name in wrappers and len(call.args) > wrappers[name]:
            text = _text(call.args[wrappers[name]])
            if text:
                names.add(text)
    return names


@functools.lru_cache(maxsize=None)
def node_parameters() -> dict[str, frozenset[str]]:
    """ROS node name -> the parameters it declares, read from exit_decision/ros/nodes/ and the
    ``declare_*`` helpers of exit_decision/ros/parameters.py."""
    tree = ast.parse(PARAMETER_HELPERS.read_text(encoding='utf-8'))
    functions = [node for node in tree.body if isinstance(node, ast.FunctionDef)]
    helpers: dict[str, set[str]] = {}
    while True:   # helpers that call helpers: until nothing changes
        found = {f.name: names for f in functions if f.name not in DECLARES
                 for names in [_declared(f, helpers)] if names}
        if found == helpers:
            break
        helpers = found
    nodes = {}
    for module in sorted(NODES_DIR.glob('*.py')):
        for cls in ast.walk(ast.parse(module.read_text(encoding='utf-8'))):
            if not isinstance(cls, ast.ClassDef):
                continue
            names = [_text(call.args[0]) for call in ast.walk(cls) if isinstance(call, ast.Call) and call.args
                     and _call_name(call) == '__init__' and isinstance(call.func, ast.Attribute)
                     and isinstance(call.func.value, ast.Call) and _call_name(call.func.value) == 'super']
            if names and names[0]:
                nodes[names[0]] = frozenset(_declared(cls, helpers) | RCLPY_PARAMETERS)
    return nodes


@functools.lru_cache(maxsize=None)
def executables() -> dict[str, tuple[str, ...]]:
    """A console script of the package (setup.py; installed into lib/exit_decision/, so ``ros2 run``
    finds it) -> the ROS nodes its process runs (none: the command line)."""
    scripts = re.findall(r"'([\w-]+) = (exit_decision[\w.]*):main'", (REPO / 'setup.py').read_text())
    return {script: NODE_NAMES.get(script, (script,)) if module.startswith('exit_decision.ros.nodes.') else ()
            for script, module in scripts}


# --- checking one snippet ------------------------------------------------------------------

def commands(text: str) -> list[list[str]]:
    """The text's commands as token lists: comments cut, split at ; && || | (not inside [...],
    where | means "or")."""
    text = re.sub(r'(^|\s)#.*', '', text)
    result, current, depth = [], [], 0
    for token in text.split():
        if token == '$':   # a console prompt
            continue
        if token.startswith('$('):   # a command substitution starts a command
            result.append(current)
            current, token = [], token[2:]
        end = token.endswith(';') and depth == 0
        token = token.rstrip(';') if end else token
        if depth == 0 and token in SEPARATORS:
            result.append(current)
            current = []
            continue
        depth += token.count('[') - token.count(']')
        depth = max(depth, 0)
        if token:
            current.append(token)
        if end:
            result.append(current)
            current = []
    result.append(current)
    return [tokens for tokens in result if tokens]


def clean(token: str) -> str:
    """A token without the brackets, quotes and punctuation of prose around it."""
    return token.strip('[]()"\'`,.:').rstrip(']')


def check_cli(arguments: list[str]) -> list[str]:
    """What in ``exit-decision <arguments>`` the parser does not have."""
    parser, path = cli_parser(), ['exit-decision']
    arguments = [clean(token) if token.startswith(('[', '(')) or token.endswith((']', ')', ',')) else token
                 for token in arguments]
    position = 0
    while (choices := subcommands(parser)) is not None:
        while position < len(arguments) and arguments[position].startswith('-'):
            if arguments[position] not in options(parser):
                return [f'{" ".join(path)} has no option {arguments[position]}']
            position += 1
        if position == len(arguments):
            return []
        name = arguments[position]
        if not PLAIN.match(name):   # a placeholder: <command>, ..., {a,b}
            return []
        if name not in choices:
            return [f'{" ".join(path)} has no command {name!r} (it has: {", ".join(choices)})']
        parser, path, position = choices[name], [*path, name], position + 1
    problems = []
    for token in arguments[position:]:
        option = OPTION.match(clean(token))
        if option and option.group(0) not in options(parser):
            problems.append(f'{" ".join(path)} has no option {option.group(0)}')
    return problems


def check_launch(arguments: list[str]) -> list[str]:
    problems = []
    for token in arguments:
        name, assigned, _ = clean(token).partition(':=')
        if assigned and IDENTIFIER.match(name) and name not in ARGUMENTS:
            problems.append(f'exit_decision.launch.py declares no argument {name!r} (it has: {", ".join(ARGUMENTS)})')
    return problems


def check_parameter(node: str, name: str | None) -> list[str]:
    declared = node_parameters()
    if node not in declared:
        return [f'no node /{node} in exit_decision (nodes: {", ".join(sorted(declared))})']
    if name is not None and name not in declared[node]:
        return [f'/{node} declares no parameter {name!r} (it declares: {", ".join(sorted(declared[node]))})']
    return []


def check_run(executable: str, arguments: list[str]) -> list[str]:
    """``ros2 run exit_decision <executable> [--ros-args -p [node:]name:=value ...]``."""
    if executable not in executables():
        return [f'exit_decision has no executable {executable!r} (it has: {", ".join(executables())})']
    if executable == 'exit-decision':
        return check_cli(arguments)
    problems = []
    for flag, value in zip(arguments, arguments[1:]):
        if flag not in ('-p', '--param'):
            continue
        target, assigned, _ = clean(value).partition(':=')
        if not assigned:
            continue
        node, _, name = target.rpartition(':')
        nodes = (node,) if node else executables()[executable]
        if not IDENTIFIER.match(name) or any(n not in node_parameters() for n in nodes):
            problems += [problem for n in nodes for problem in check_parameter(n, None)]
            continue
        if not any(name in node_parameters()[n] for n in nodes):
            problems.append(f'{executable} ({", ".join(nodes)}) declares no parameter {name!r}')
    return problems


def check_command(tokens: list[str]) -> list[str]:
    """What in one command a reader could not type: a command, option, launch argument,
    executable or parameter the code does not have. Other commands are not looked at."""
    for start, token in enumerate(tokens):
        rest = tokens[start + 1:]
        if token.rpartition('/')[2] == 'exit-decision':
            return check_cli(rest)
        if token.rpartition('/')[2].startswith('python') and rest[:2] == ['-m', 'exit_decision']:
            return check_cli(rest[2:])
        if token == 'scripts/main' or token.endswith('/scripts/main'):
            return check_cli(['stack', *rest])
        if token == 'ros2' and rest[:1] == ['launch']:
            target = rest[1:3] if rest[1:2] == ['exit_decision'] else rest[1:2]
            if target and target[-1].endswith('exit_decision.launch.py'):
                return check_launch(rest[1 + len(target):])
            return []
        if token == 'ros2' and rest[:1] == ['param'] and len(rest) >= 3:
            node = rest[2]
            if not node.startswith('/') or not PLAIN.match(node.rpartition('/')[2]):
                return []   # a placeholder: /<node>
            name = rest[3] if rest[1] in ('set', 'get', 'describe') and len(rest) > 3 else None
            if name is not None and not IDENTIFIER.match(name):
                name = None
            return check_parameter(node.rpartition('/')[2], name)
        if token == 'ros2' and rest[:2] == ['run', 'exit_decision'] and len(rest) > 2:
            return check_run(rest[2], rest[3:]) if PLAIN.match(rest[2]) else []
    return []


def command_problems(path: Path) -> list[str]:
    problems = []
    for snippet in read_markdown(path)[0]:
        if snippet.section and not snippet.fenced and OPTION.match(snippet.text):
            for problem in check_cli([*snippet.section, *snippet.text.split()]):
                problems.append(f'{shown(path)}:{snippet.line}: '
                                f'`{snippet.text}` under `exit-decision {" ".join(snippet.section)}`: {problem}')
            continue
        for tokens in commands(snippet.text):
            problems += [f'{shown(path)}:{snippet.line}: '
                         f'`{" ".join(tokens)}`: {problem}' for problem in check_command(tokens)]
    return problems


LINK = re.compile(r'!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+["\'(][^)]*)?\)')
REFERENCE = re.compile(r'^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)')


def link_problems(path: Path) -> list[str]:
    """Relative links (inline and reference style, images too) that point to nothing."""
    problems = []
    for number, line in read_markdown(path)[1]:
        targets = LINK.findall(line) + REFERENCE.findall(line)
        for target in targets:
            if re.match(r'^[a-z][a-z0-9+.-]*:', target, re.IGNORECASE) or target.startswith('#'):
                continue   # http(s), mailto, ...; an anchor of this page
            file = target.partition('#')[0].partition('?')[0].replace('%20', ' ')
            if not (path.parent / file).exists():
                problems.append(f'{shown(path)}:{number}: link [..]({target}): no such file')
    return problems


# --- the tests -----------------------------------------------------------------------------

def test_every_command_option_launch_argument_and_parameter_in_the_docs_exists():
    problems = [problem for path in documents() for problem in command_problems(path)]
    assert not problems, 'commands in the docs the code does not have:\n' + '\n'.join(problems)


def test_every_relative_link_in_the_docs_points_to_a_file():
    problems = [problem for path in documents() for problem in link_problems(path)]
    assert not problems, 'dead links:\n' + '\n'.join(problems)


def leaf_commands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(command path, its parser) for every command that takes no further command."""
    choices = subcommands(parser)
    if choices is None:
        yield path, parser
        return
    for name, child in choices.items():
        yield from leaf_commands(child, (*path, name))


def test_the_command_line_page_has_a_section_for_every_command_naming_each_of_its_options():
    documented: dict[tuple[str, ...], set[str]] = {}
    for snippet in read_markdown(REPO / 'docs' / 'cli.md')[0]:
        if snippet.section and not snippet.fenced:
            documented.setdefault(snippet.section, set()).update(re.findall(r'--[a-z][a-z0-9-]*', snippet.text))
    missing = [f'exit-decision {" ".join(path)}: ' + (', '.join(sorted(absent)) if path in documented else
                                                      'no section (a heading with `exit-decision <command>`)')
               for path, parser in leaf_commands(cli_parser())
               for absent in [options(parser) - {'-h', '--help'} - documented.get(path, set())]
               if absent or path not in documented]
    assert not missing, 'docs/cli.md does not document:\n' + '\n'.join(missing)


def test_the_nodes_parameters_are_read_from_their_code():
    """The list the checker uses: every node of the stack, with what the code declares."""
    declared = node_parameters()
    assert {node for nodes in NODE_NAMES.values() for node in nodes} <= set(declared)
    assert {'player'} <= set(declared)
    assert {'mode', 'reward_weights', 'algorithm', 'algorithms', 'modes', 'policy_dir', 'config_dir',
            'thread_priority', 'cpu_affinity'} <= declared['decision_node']
    # through a local wrapper of declare (sumo_bridge's p(...)) and through the helpers
    assert {'timing', 'command_timeout', 'realtime_factor', 'episodes', 'seed', 'cav_driver', 'startup_timeout',
            'thread_priority', 'cpu_affinity', 'config_dir'} <= declared['sumo_bridge']
    assert {'bag_path', 'rate', 'loop', 'wait_for_subscribers', 'cpu_affinity'} <= declared['player']
    assert 'mode' not in declared['graph_builder'] and 'thread_priority' not in declared['recorder']
    assert executables()['graph_and_decision'] == ('graph_builder', 'decision_node')
    assert executables()['exit-decision'] == ()


BROKEN = """\
# A page with mistakes

Run `exit-decision stack --no-such-option` or `exit-decision bench ros --stepz 10`; a span can wrap: `exit-decision
run --scenario-variant density_1.45 --no-such-option`.

```bash
exit-decision nosuch --episodes 1
exit-decision fixture nosuch
scripts/main --mode CONI --swich-to AGGI   # the second option is misspelt
ros2 launch exit_decision exit_decision.launch.py mode:=AGGI nosuch:=1
ros2 param set /decision_node modee AGGI
ros2 param get /no_such_node mode
ros2 run exit_decision decision_node --ros-args -p decision_node:nosuch:=1
ros2 run exit_decision no_such_executable
ros2 run exit_decision exit-decision replay <bag> --rebuild-graphs
```

See [the design](design.md#learning), [a missing page](missing.md) and
![a figure](figures/gone.png).

## `exit-decision train`

| option | what |
|---|---|
| `--episodes N` | fine |
| `--no-such-option` | not an option of train |
"""

CORRECT = """\
# A page without mistakes

`exit-decision` alone, `exit-decision <command> --help`, `exit-decision stack --start-mode CONI --no-visualizer`.

```console
$ python -m exit_decision bench ros --steps 10 [--no-cpu-split | --thread-priority 10]
$ .venv/bin/exit-decision bag repair BAG; exit-decision fixture record --out /tmp/f && exit-decision --help
$ scripts/main --switch-to AGGI --switch-at 200   # not --bogus: a comment
$ ros2 launch exit_decision exit_decision.launch.py mode:=AGGI use_sim_time:=true
$ ros2 launch ... --show-args
$ ros2 param set /decision_node mode AGGI
$ ros2 param get /sumo_bridge use_sim_time
$ ros2 run exit_decision graph_and_decision --ros-args -p decision_node:mode:=CONP -p cpu_affinity:=[0]
$ ros2 run exit_decision player --ros-args -p bag_path:=<bag> -p rate:=2.0
$ ros2 run exit_decision exit-decision show <bag> --fps 5
```

```python
subprocess.run(['exit-decision', 'stack', '--bogus'])   # not a shell block: not read
```

```json
{"command": "exit-decision stack --bogus"}
```

[design](design.md#learning), [web](https://example.org/missing.md), [anchor](#a-page), `[code](missing.md)`.

## `exit-decision bag repair BAG`

`--help`

## `exit-decision bench [sim|learning|sweep|ros]`

`--steps N`, `--thread-priority 10`, `--no-cpu-split`

## Another section

`--no-such-option` here belongs to no command.
"""


def test_the_checks_find_each_kind_of_mistake_and_name_its_file_and_line(tmp_path):
    (tmp_path / 'design.md').write_text('# Design\n')
    broken = tmp_path / 'broken.md'
    broken.write_text(BROKEN)
    problems = command_problems(broken) + link_problems(broken)
    expected = [
        (3, '`exit-decision stack --no-such-option`: exit-decision stack has no option --no-such-option'),
        (3, '`exit-decision bench ros --stepz 10`: exit-decision bench has no option --stepz'),
        (3, '`exit-decision run --scenario-variant density_1.45 --no-such-option`: exit-decision run has no option '
            '--no-such-option'),
        (7, "exit-decision has no command 'nosuch'"),
        (8, "exit-decision fixture has no command 'nosuch'"),
        (9, 'exit-decision stack has no option --swich-to'),
        (10, "exit_decision.launch.py declares no argument 'nosuch'"),
        (11, "/decision_node declares no parameter 'modee'"),
        (12, 'no node /no_such_node in exit_decision'),
        (13, "decision_node (decision_node) declares no parameter 'nosuch'"),
        (14, "exit_decision has no executable 'no_such_executable'"),
        (15, 'exit-decision replay has no option --rebuild-graphs'),
        (26, '`--no-such-option` under `exit-decision train`: exit-decision train has no option --no-such-option'),
        (18, 'link [..](missing.md): no such file'),
        (19, 'link [..](figures/gone.png): no such file'),
    ]
    assert len(problems) == len(expected), '\n'.join(problems)
    for problem, (line, text) in zip(problems, expected):
        assert problem.startswith(f'{broken}:{line}: ') and text in problem, (problem, line, text)

    correct = tmp_path / 'correct.md'
    correct.write_text(CORRECT)
    assert command_problems(correct) + link_problems(correct) == []


def test_the_readme_is_under_150_lines():
    lines = (REPO / 'README.md').read_text(encoding='utf-8').splitlines()
    assert len(lines) < 150, f'README.md: {len(lines)} lines; a newcomer reads it in five minutes: under 150'
