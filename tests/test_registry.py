"""The package's structure: an acyclic import graph, an algorithm added as one file plus one registry line, presets
that live with their env and hold no seeds."""

from __future__ import annotations

import ast
import json
import pathlib
import textwrap

import pytest
from jaxdeconf.envs import REGISTRY as ENVS
from jaxdeconf.envs import make

from jaxdeconf import algos, memory
from jaxdeconf.errors import ConfigError
from jaxdeconf.files import read_rows
from jaxdeconf.resolve import build, env_presets
from jaxdeconf.train import train_algorithm

ROOT = pathlib.Path(__file__).parents[1]
CARTPOLE = f"{ROOT / 'examples' / 'cartpole.py'}:ConfoundedCartPole"


def _module_files() -> dict[str, pathlib.Path]:
    """Every module of the installed package by dotted name: src/jaxdeconf and the top-level envs/ folder."""
    out = {}
    for base, package in ((ROOT / "src" / "jaxdeconf", "jaxdeconf"), (ROOT / "envs", "jaxdeconf.envs")):
        for path in base.rglob("*.py"):
            parts = path.relative_to(base).with_suffix("").parts
            parts = parts[:-1] if parts[-1] == "__init__" else parts
            out[".".join((package, *parts))] = path
    return out


def _type_checking_lines(tree: ast.Module) -> set[int]:
    """Line numbers inside ``if TYPE_CHECKING:`` blocks: imports for annotations only, never executed."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING":
            for child in node.body:
                lines.update(range(child.lineno, (child.end_lineno or child.lineno) + 1))
    return lines


def import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports anywhere in its body (functions' lazy imports included)."""
    modules = _module_files()
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text())
        skip = _type_checking_lines(tree)
        found: set[str] = set()
        for node in ast.walk(tree):
            if getattr(node, "lineno", None) in skip:
                continue
            if isinstance(node, ast.Import):
                found.update(a.name for a in node.names if a.name in modules)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                subs = {f"{node.module}.{a.name}" for a in node.names} & modules.keys()
                found.update(subs or ({node.module} & modules.keys()))
        graph[name] = found - {name}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as a list of modules (first = last), or None: depth-first search with colours."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt):], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_find_cycle_finds_a_planted_cycle_and_only_then():
    """The checker itself: a -> b -> c -> a is found, the same graph without c -> a is clean."""
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_the_package_import_graph_has_no_cycle():
    """No module imports, even lazily inside a function, a module that imports it back, directly or through others;
    the shared errors sit in a leaf module and the config schema knows no algorithm."""
    graph = import_graph()
    assert graph["jaxdeconf.errors"] == set()
    assert "jaxdeconf.algos" not in graph["jaxdeconf.config"]
    assert "jaxdeconf.config" in graph["jaxdeconf.algos.base"]  # The walker sees real edges.
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))


DUMMY = '''
"""A dummy algorithm in a file of its own: naive BC whose learning rate is its own setting."""

import dataclasses

import optax

from jaxdeconf.algos.base import make_optimizer
from jaxdeconf.algos.bc import BehaviourCloning
from jaxdeconf.config import field


@dataclasses.dataclass(frozen=True)
class DummyConfig:
    """The dummy's own section."""

    lr: float = field(1e-3, ">0")  # Its policy's learning rate.


@dataclasses.dataclass(frozen=True)
class Dummy(BehaviourCloning):
    """bc with ``dummy.lr``."""

    settings = ("dummy", DummyConfig)

    @property
    def policy_tx(self) -> optax.GradientTransformation:
        """AdamW at the dummy's own rate."""
        return make_optimizer(self.config.dummy.lr, self.config.train.weight_decay, self.config.train.policy_clip)
'''


@pytest.mark.timeout(300)
def test_an_algorithm_is_one_file_and_one_registry_line(tmp_path, monkeypatch):
    """A new file plus one line in ``algos.REGISTRY`` is all it takes: the CLI's config accepts the algorithm and its
    own section (``dummy.lr``), validates it, estimates its memory, and trains it for one chunk."""
    (tmp_path / "dummy_algo.py").write_text(textwrap.dedent(DUMMY))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(algos.REGISTRY, "dummy", algos.Entry("dummy_algo", "Dummy", {"view": "imitator"}))  # One line.
    from conftest import TINY

    config = build("bandit", "cpu", ("dummy",), 1, {**TINY, "train.iterations": "2", "dummy.lr": "0.01"})
    assert config.dummy.lr == 0.01 and "dummy" in config.to_dict()
    with pytest.raises(ConfigError, match=r"dummy.lr=-1.0 is not allowed: need a number > 0"):
        build("bandit", "cpu", ("dummy",), 1, {"dummy.lr": "-1"})
    env, params = make("bandit", horizon=10)
    assert memory.estimate(config, "dummy", env, params).total > 0
    train_algorithm(config, "dummy", tmp_path / "run", progress=False)
    rows = read_rows(tmp_path / "run" / "metrics.jsonl")
    assert [r["iteration"] for r in rows] == [1, 2] and 0.0 <= rows[-1]["eval_return"] <= 10.0  # 10 pulls.


@pytest.mark.parametrize("env", [*ENVS, CARTPOLE])
def test_presets_live_with_their_env_and_hold_no_seeds(env):
    """Every env declares its presets on its class; none chooses seeds, so the held-out seeds a user asks for
    (``--set seed_start=100``) are never overridden by a preset."""
    presets = env_presets(env)
    assert "cpu" in presets
    for name, fields in presets.items():
        assert not {"seeds", "seed_start"} & set(fields), (env, name)
        build(env, name, ("bc",), 1, {})  # Every preset resolves and validates.


def test_each_deconfounded_method_is_one_configuration_on_every_env_and_preset():
    """``dil`` (the paper's) and ``dil_plus`` each read their networks' inputs the same way on every env and preset:
    a preset sets sizes and budgets, never a method's section, so the resolved sections equal their defaults."""
    from jaxdeconf.algos.dil import DilConfig
    from jaxdeconf.algos.dil_plus import DilPlusConfig

    assert vars(DilConfig()) != vars(DilPlusConfig())  # Two methods, not one under two names.
    for env in (*ENVS, CARTPOLE):
        for preset in env_presets(env):
            config = build(env, preset, ("dil", "dil_plus"), 1, {})
            assert (config.dil, config.dil_plus) == (DilConfig(), DilPlusConfig()), (env, preset)


def test_an_env_without_presets_is_refused_by_name(tmp_path):
    """A user's env that declares no presets gets a one-line error naming it, never another env's presets."""
    (tmp_path / "bare.py").write_text(textwrap.dedent('''
        from jaxdeconf.envs.bandit import Bandit

        class Bare(Bandit):
            presets = {}
    '''))
    with pytest.raises(ConfigError, match=r"env '.*bare.py:Bare' declares no presets; give its class a `presets`"):
        build(f"{tmp_path / 'bare.py'}:Bare", "cpu", ("bc",), 1, {})


def test_saved_config_lists_every_registered_section():
    """A results folder's config.json holds the algorithm-owned sections beside model and train."""
    saved = json.loads(json.dumps(build("bandit", "cpu", ("bc",), 1, {}).to_dict()))
    assert {"model", "train", *algos.settings_sections()} <= set(saved)


def test_a_shorter_run_than_the_presets_chunk_gets_one_chunk_and_a_set_chunk_is_checked():
    """A preset's chunk follows a shorter ``train.iterations``; a chunk the user sets past the run is refused."""
    assert build("bandit", "cpu", ("bc",), 1, {"train.iterations": "21"}).train.chunk == 21
    assert build("bandit", "cpu", ("bc",), 1, {"train.iterations": "200"}).train.chunk == 25
    with pytest.raises(ConfigError, match=r"train.chunk=30 is not allowed: need at most train.iterations=21"):
        build("bandit", "cpu", ("bc",), 1, {"train.iterations": "21", "train.chunk": "30"})
