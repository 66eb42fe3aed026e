"""The arrows between dusty_jax's modules run one way (the house of the style
guide at ../shared/STYLE.md, beside the repository, not in it), and a model
variant is asked what it is, never compared by name.

Every import counts, the ones inside functions too: an import deferred to
call time is still a dependency, and a cycle of them is still a cycle.
"""

import ast
import os

import pytest

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', 'dusty_jax')
REPO = os.path.dirname(ROOT)


def _modules() -> dict:
  """{module name: path} of every module of the package."""
  out = {}
  for d, _, files in os.walk(ROOT):
    for f in files:
      if f.endswith('.py'):
        rel = os.path.relpath(os.path.join(d, f), os.path.dirname(ROOT))[:-3]
        name = rel.replace(os.sep, '.')
        out[name[:-len('.__init__')] if name.endswith('.__init__') else name] = \
            os.path.join(d, f)
  return out


def _graph() -> dict:
  """{module: set of dusty_jax modules it imports}.

  ``from pkg import sub`` of a submodule depends on ``pkg.sub`` only; of any
  other name (``from dusty_jax.tools import parse``) on the package, whose
  __init__ then counts like a module. The top package ``dusty_jax`` (the
  public API, importing half the library) is left out as a target: every
  ``from dusty_jax import x`` goes through it.
  """
  modules = _modules()
  graph = {}
  for name, path in modules.items():
    deps = set()
    tree = ast.parse(open(path).read(), path)
    for node in ast.walk(tree):
      if isinstance(node, ast.Import):
        deps.update(a.name for a in node.names)
      elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
        for a in node.names:
          sub = f'{node.module}.{a.name}'
          deps.add(sub if sub in modules else node.module)
    graph[name] = {d for d in deps if d in modules and d not in (name, 'dusty_jax')}
  return graph


GRAPH = _graph()


def test_the_graph_is_read():
  assert GRAPH['dusty_jax.trainer'] >= {'dusty_jax.models', 'dusty_jax.losses',
                                        'dusty_jax.augment', 'dusty_jax.checkpoint'}
  assert 'dusty_jax.tools' in GRAPH['dusty_jax.tools.invert']  # the package's helpers
  assert 'dusty_jax.generator' in GRAPH['dusty_jax.pretrained']


def test_no_import_cycle():
  state = {}

  def visit(node, path):
    state[node] = 'open'
    for dep in sorted(GRAPH[node]):
      if state.get(dep) == 'open':
        cycle = path[path.index(dep):] + [dep]
        pytest.fail('import cycle: ' + ' -> '.join(cycle))
      if dep not in state:
        visit(dep, path + [dep])
    state[node] = 'done'

  for node in sorted(GRAPH):
    if node not in state:
      visit(node, [node])


def _reach(name) -> set:
  seen, todo = set(), [name]
  while todo:
    for dep in GRAPH[todo.pop()]:
      if dep not in seen:
        seen.add(dep)
        todo.append(dep)
  return seen


@pytest.mark.parametrize('module, banned', [
    # The one place that knows about orbax knows nothing of ours.
    ('dusty_jax.checkpoint', 'dusty_jax.'),
    # Loading a trained generator needs no training and no data pipeline.
    ('dusty_jax.generator', ('dusty_jax.trainer', 'dusty_jax.losses', 'dusty_jax.augment',
                             'dusty_jax.data.pipeline', 'dusty_jax.data.synthetic')),
    ('dusty_jax.sampling', ('dusty_jax.trainer', 'dusty_jax.data.pipeline')),
    ('dusty_jax.inversion', ('dusty_jax.trainer', 'dusty_jax.data.pipeline')),
])
def test_what_a_module_never_reaches(module, banned):
  bad = sorted(m for m in _reach(module) if m.startswith(banned))
  assert not bad, f'{module} reaches {bad}'


def test_data_never_imports_the_model_and_metrics_never_training():
  model_side = ('dusty_jax.models', 'dusty_jax.trainer', 'dusty_jax.generator',
                'dusty_jax.sampling', 'dusty_jax.inversion', 'dusty_jax.layers')
  training = ('dusty_jax.trainer', 'dusty_jax.train', 'dusty_jax.losses',
              'dusty_jax.augment', 'dusty_jax.parallel', 'dusty_jax.checkpoint')
  for name, deps in GRAPH.items():
    if name.startswith('dusty_jax.data.'):
      assert not {d for d in deps if d.startswith(model_side)}, name
    if name.startswith('dusty_jax.metrics'):
      assert not {d for d in deps if d.startswith(training)}, name


def test_only_command_lines_import_command_lines():
  for name, deps in GRAPH.items():
    if name.startswith('dusty_jax.tools') or name == 'dusty_jax.train':
      continue
    assert not {d for d in deps if d.startswith('dusty_jax.tools') or d == 'dusty_jax.train'}, name


MODEL_NAMES = {'baseline', 'dusty1', 'dusty2'}


def _name_comparisons(path: str) -> list:
  """Lines of ``path`` comparing something with a model name (``==``, ``!=``,
  ``in`` a tuple of names, ...)."""
  out = []
  for node in ast.walk(ast.parse(open(path).read(), path)):
    if not isinstance(node, ast.Compare):
      continue
    for operand in [node.left] + node.comparators:
      consts = operand.elts if isinstance(operand, (ast.Tuple, ast.List, ast.Set)) else [operand]
      if any(isinstance(c, ast.Constant) and c.value in MODEL_NAMES for c in consts):
        out.append(node.lineno)
  return out


def _python_files(*dirs):
  for top in dirs:
    for d, _, files in os.walk(os.path.join(REPO, top)):
      yield from (os.path.join(d, f) for f in files if f.endswith('.py'))


def test_the_name_check_sees_comparisons(tmp_path):
  p = tmp_path / 'x.py'
  p.write_text("a = m == 'dusty2'\nb = m in ('baseline', 'x')\nc = {'dusty1': 1}\n")
  assert _name_comparisons(str(p)) == [1, 2]


def test_only_models_compares_model_names():
  """Callers ask models.get_variant(name) what a variant is (its heads,
  whether it has a measurability, ...), so a new variant touches models.py,
  a config and tests."""
  models_py = os.path.join(ROOT, 'models.py')
  bad = {os.path.relpath(p, REPO): lines
         for p in _python_files('dusty_jax', 'benchmarks', 'experiments')
         if p != models_py and (lines := _name_comparisons(p))}
  assert not bad, f'model names compared outside models.py: {bad}'




def _unexplained_lazy_imports(path: str) -> list:
  """Lines of ``path`` importing a dusty_jax module inside a function with
  no comment on that line or the one above (the reason it waits)."""
  lines = open(path).read().splitlines()
  out = []
  for fn in ast.walk(ast.parse('\n'.join(lines), path)):
    if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
      continue
    for node in ast.walk(fn):
      names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
               [node.module or ''] if isinstance(node, ast.ImportFrom) else [])
      if not any(n.startswith('dusty_jax') for n in names):
        continue
      here, above = lines[node.lineno - 1], lines[node.lineno - 2].strip()
      if '#' not in here and not above.startswith('#'):
        out.append(node.lineno)
  return out


def test_the_lazy_import_check_sees_them(tmp_path):
  p = tmp_path / 'x.py'
  p.write_text('import os\n\ndef f():\n  from dusty_jax import a\n  import os\n'
               '  # the reason\n  from dusty_jax import b\n  import dusty_jax.c  # why\n')
  assert _unexplained_lazy_imports(str(p)) == [4]


def test_lazy_imports_say_why():
  """Imports sit at the top of a module, so its first lines show what it
  depends on; one inside a function (import cost, an optional dependency,
  an order such as distributed init) says why on its line or the one above."""
  bad = {os.path.relpath(p, REPO): lines for p in _python_files('dusty_jax')
         if (lines := _unexplained_lazy_imports(p))}
  assert not bad, f'function-level imports without a reason: {bad}'
