"""The arrows between dusty_jax's modules run one way (the house of the style
guide at ../shared/STYLE.md, beside the repository, not in it), and a model
variant is asked what it is, never compared by name.

Every import counts, the ones inside functions too: an import deferred to
call time is still a dependency, and a cycle of them is still a cycle.
"""

import ast
import importlib
import importlib.util
import os
import re
import types

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
                                        'dusty_jax.augment', 'dusty_jax.checkpoint',
                                        'dusty_jax.drops'}
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
    # The one place that knows about orbax knows nothing of ours but files
    # and errors, which know nothing of ours either.
    ('dusty_jax.checkpoint', tuple(m for m in GRAPH if m not in (
        'dusty_jax', 'dusty_jax.files', 'dusty_jax.errors'))),
    ('dusty_jax.files', 'dusty_jax.'),
    ('dusty_jax.errors', 'dusty_jax.'),
    # Loading a trained generator needs no training and no data pipeline.
    ('dusty_jax.generator', ('dusty_jax.trainer', 'dusty_jax.losses', 'dusty_jax.augment',
                             'dusty_jax.data.pipeline', 'dusty_jax.data.synthetic')),
    ('dusty_jax.sampling', ('dusty_jax.trainer', 'dusty_jax.data.pipeline')),
    ('dusty_jax.inversion', ('dusty_jax.trainer', 'dusty_jax.data.pipeline')),
    # The point-drop terms are pure functions of arrays: configs reads their
    # options, the trainer calls them; they know neither, nor the networks.
    ('dusty_jax.drops', ('dusty_jax.trainer', 'dusty_jax.configs', 'dusty_jax.models',
                         'dusty_jax.augment', 'dusty_jax.losses', 'dusty_jax.data')),
])
def test_what_a_module_never_reaches(module, banned):
  bad = sorted(m for m in _reach(module) if m.startswith(banned))
  assert not bad, f'{module} reaches {bad}'


def test_data_never_imports_the_model_and_metrics_never_training():
  model_side = ('dusty_jax.models', 'dusty_jax.trainer', 'dusty_jax.generator',
                'dusty_jax.sampling', 'dusty_jax.inversion', 'dusty_jax.layers')
  training = ('dusty_jax.trainer', 'dusty_jax.train', 'dusty_jax.losses',
              'dusty_jax.augment', 'dusty_jax.parallel', 'dusty_jax.checkpoint',
              'dusty_jax.drops')
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


def test_the_library_changes_no_process_wide_hook():
  """A library leaves the asyncio event-loop policy and the interpreter's
  hook for unraisable errors to the program (STYLE.md)."""
  bad = {os.path.relpath(p, REPO): word for p in _python_files('dusty_jax')
         for word in ('set_event_loop_policy', 'unraisablehook') if word in open(p).read()}
  assert not bad, f'process-wide hooks swapped: {bad}'


def test_only_the_command_lines_switch_the_compilation_cache_on():
  """JAX's persistent cache is a process-wide setting: cli.run switches it
  on where a command starts, a library user's program with
  dusty_jax.enable_compilation_cache() (the public API's name for it); no
  computing module imports it."""
  assert {name for name, deps in GRAPH.items() if 'dusty_jax.xla_cache' in deps} == {
      'dusty_jax', 'dusty_jax.cli'}


def _runs_through_cli(path: str) -> bool:
  """Whether ``path`` calls ``cli.run`` or ``tools.run`` (the same function)."""
  return any(isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
             and ast.unparse(node.func) in ('cli.run', 'tools.run')
             for node in ast.walk(ast.parse(open(path).read(), path)))


def test_every_command_line_runs_through_cli():
  """So each starts with the compilation cache on and ends a user's error in
  one line."""
  commands = [os.path.join(ROOT, 'train.py')] + [
      os.path.join(ROOT, 'tools', f) for f in os.listdir(os.path.join(ROOT, 'tools'))
      if f.endswith('.py') and f != '__init__.py']
  assert len(commands) >= 7
  assert not _runs_through_cli(os.path.join(ROOT, 'inversion.py'))  # the check can say no
  bad = [os.path.relpath(p, REPO) for p in commands if not _runs_through_cli(p)]
  assert not bad, f'command lines not run through cli.run: {bad}'


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


RESEARCH = os.path.join(REPO, 'benchmarks', 'research')


def _research_modules() -> set:
  """Module names of the research record's scripts (each imports its
  siblings by bare name, as the product benchmarks import common)."""
  return {f[:-3] for _, _, files in os.walk(RESEARCH) for f in files if f.endswith('.py')}


def _research_imports(path: str, research: set) -> list:
  """Lines of ``path`` that import the research record: a ``research``
  package, one of its scripts by name, or a sys.path entry naming it."""
  out = []
  for node in ast.walk(ast.parse(open(path).read(), path)):
    names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
             [node.module or ''] if isinstance(node, ast.ImportFrom) else [])
    if any(n.split('.')[0] in research | {'research'} or n.startswith('benchmarks.research')
           for n in names):
      out.append(node.lineno)
    if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
        and ast.unparse(node.func.value) == 'sys.path'
        and any(isinstance(c, ast.Constant) and 'research' in str(c.value)
                for a in node.args for c in ast.walk(a))):
      out.append(node.lineno)
  return out


def test_the_research_import_check_sees_them(tmp_path):
  p = tmp_path / 'x.py'
  p.write_text('import common\nimport drops_screen\nfrom benchmarks.research.speed import x\n'
               "import sys\nsys.path.insert(0, 'benchmarks/research/drops')\n"
               'from dusty_jax import drops\n')
  assert _research_imports(str(p), {'drops_screen'}) == [2, 3, 5]


def test_nothing_of_the_product_imports_the_research_record():
  """benchmarks/research/ holds probes and their records; the library, the
  tests and the product benchmarks (benchmarks/*.py) never depend on it."""
  research = _research_modules()
  assert {'placement_curve', 'conv_forms'} <= research
  product = list(_python_files('dusty_jax', 'tests')) + [
      os.path.join(REPO, 'benchmarks', f) for f in os.listdir(os.path.join(REPO, 'benchmarks'))
      if f.endswith('.py')]
  bad = {os.path.relpath(p, REPO): lines for p in product
         if (lines := _research_imports(p, research))}
  assert not bad, f'imports of benchmarks/research: {bad}'


_SCOPES = (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)
_NOT_FOLLOWED = object()


def _bindings(scope) -> tuple:
  """({name: (line, what it imports)}, {names bound otherwise}) of one
  scope, its nested scopes left out. What an import takes is
  ('dusty_jax.data.pipeline',) or ('dusty_jax.data', 'pipeline')."""
  imports, other = {}, set()
  if isinstance(scope, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
    other |= {a.arg for a in ast.walk(scope.args) if isinstance(a, ast.arg)}
  todo = list(scope.body) if isinstance(scope.body, list) else [scope.body]
  while todo:
    node = todo.pop()
    if isinstance(node, ast.Import):
      for a in node.names:
        imports[a.asname or a.name.split('.')[0]] = (node.lineno, (a.name,))
    elif isinstance(node, ast.ImportFrom) and node.level == 0:
      for a in node.names:
        imports[a.asname or a.name] = (node.lineno, (node.module, a.name))
    elif isinstance(node, _SCOPES):
      other.add(getattr(node, 'name', None))
      continue
    elif isinstance(node, ast.Name) and not isinstance(node.ctx, ast.Load):
      other.add(node.id)
    todo.extend(ast.iter_child_nodes(node))
  return imports, other


def _top_names(path: str) -> set:
  """The names a script defines at its top level (functions, classes,
  assignments, imports)."""
  imports, other = _bindings(ast.parse(open(path).read(), path))
  return set(imports) | other


def _unresolved(path: str, folders=()) -> list:
  """'LINE: what' for each name ``path`` takes from dusty_jax, from a script
  beside it (or in ``folders``: benchmarks/ for common.py) or from an
  installed package that is not there: an import, or an attribute of an
  imported module used anywhere in the script (``configs.study(...)``). A
  name a scope also binds otherwise (a local ``sensor``) is not followed."""
  siblings = {}
  for d in (os.path.dirname(path),) + tuple(folders):
    siblings.update({f[:-3]: os.path.join(d, f) for f in os.listdir(d)
                     if f.endswith('.py') and f[:-3] not in siblings})

  def find(what):
    """The module object, a script's path, or None (gone); _NOT_FOLLOWED for
    what this check does not look into (a package outside dusty_jax, a
    script's function)."""
    module, *name = what
    top = module.split('.')[0]
    if top in siblings and top == module:
      if not name:
        return siblings[top]
      return _NOT_FOLLOWED if name[0] in _top_names(siblings[top]) else None
    if top != 'dusty_jax':
      return _NOT_FOLLOWED if importlib.util.find_spec(top) else None
    try:
      obj = importlib.import_module(module)
    except ImportError:
      return None
    return attribute(obj, name[0]) if name else obj

  def attribute(obj, name):
    if hasattr(obj, name):
      return getattr(obj, name)
    try:
      return importlib.import_module(f'{obj.__name__}.{name}')
    except ImportError:
      return None

  problems = []

  def visit(scope, stack):
    imports, other = _bindings(scope)
    stack = stack + [(imports, other)]
    for line, what in imports.values():
      if find(what) is None:
        problems.append(f'{line}: import of {".".join(what)}')
    todo = list(ast.iter_child_nodes(scope))
    while todo:
      node = todo.pop()
      if isinstance(node, _SCOPES):
        visit(node, stack)
        continue
      todo.extend(ast.iter_child_nodes(node))
      if not isinstance(node, ast.Attribute):
        continue
      chain, base = [], node
      while isinstance(base, ast.Attribute):
        chain.insert(0, base.attr)
        base = base.value
      if not isinstance(base, ast.Name):
        continue
      where = next((s for s in reversed(stack) if base.id in s[0] or base.id in s[1]), None)
      if where is None or base.id in where[1] or base.id not in where[0]:
        continue
      what = where[0][base.id][1]
      if len(what) == 1 and what[0].startswith(base.id + '.'):  # import a.b binds a
        what = (base.id,)
      obj = find(what)
      if isinstance(obj, str):  # a script beside it: its top-level names
        if chain[0] not in _top_names(obj):
          problems.append(f'{node.lineno}: {base.id}.{chain[0]}')
        continue
      for i, attr in enumerate(chain):
        if not isinstance(obj, types.ModuleType):
          break
        obj = attribute(obj, attr)
        if obj is None:
          problems.append(f'{node.lineno}: {base.id}.{".".join(chain[:i + 1])}')
          break

  visit(ast.parse(open(path).read(), path), [])
  return sorted(set(problems), key=lambda p: (int(p.split(':')[0]), p))


def test_the_resolution_check_sees_names_that_left(tmp_path):
  (tmp_path / 'helper.py').write_text('def kept():\n  pass\n')
  p = tmp_path / 'x.py'
  p.write_text('import helper\nimport gone_script\nfrom helper import kept, dropped\n'
               'from dusty_jax import configs, sensor\nimport dusty_jax.data.gone\n\n'
               'def f(sensor):\n  return sensor.shape, configs.study(), helper.nothing\n\n'
               'def g():\n  from dusty_jax.data import pipeline\n'
               '  return pipeline.default_cache(), dusty_jax.invert, dusty_jax.nvert, '
               'sensor.get_sensor, configs.validate\n')
  assert _unresolved(str(p)) == ['2: import of gone_script', '3: import of helper.dropped',
                                 '5: import of dusty_jax.data.gone', '8: configs.study',
                                 '8: helper.nothing', '12: dusty_jax.nvert']


def test_every_research_script_resolves_against_the_package():
  """A research script that calls what left the library (configs.study)
  leaves the tree, its record kept by the README naming the commit it ran
  at; those that stay still import what they take."""
  scripts = sorted(p for p in _python_files(os.path.join('benchmarks', 'research')))
  assert len(scripts) >= 10
  bad = {os.path.relpath(p, REPO): problems for p in scripts
         if (problems := _unresolved(p, (BENCHMARKS,)))}
  assert not bad, f'research scripts taking names that are gone: {bad}'


def _documents() -> list:
  """README.md and every Markdown file under benchmarks/."""
  docs = [os.path.join(REPO, 'README.md')]
  for d, _, files in os.walk(os.path.join(REPO, 'benchmarks')):
    docs += [os.path.join(d, f) for f in files if f.endswith('.md')]
  return docs


def _anchors(path: str) -> set:
  """GitHub's anchors of a Markdown file's headings."""
  out = set()
  for line in open(path).read().split('\n'):
    if line.startswith('#'):
      title = line.lstrip('#').strip().lower()
      out.add(re.sub(r'[^\w\- ]', '', title).replace(' ', '-'))
  return out


def _broken_links(path: str) -> list:
  """Relative links and images of a Markdown file whose target (file, or
  heading of a Markdown file) does not exist."""
  text = re.sub(r'```.*?```', '', open(path).read(), flags=re.S)
  text = re.sub(r'`[^`\n]*`', '', text)
  out = []
  for target in re.findall(r'\]\(([^)\s]+)\)', text):
    if re.match(r'[a-z]+:', target):
      continue
    file, _, anchor = target.partition('#')
    full = os.path.normpath(os.path.join(os.path.dirname(path), file)) if file else path
    if not os.path.exists(full):
      out.append(target)
    elif anchor and full.endswith('.md') and anchor not in _anchors(full):
      out.append(target)
  return out


def test_the_link_check_sees_broken_links(tmp_path):
  (tmp_path / 'a.png').write_bytes(b'')
  (tmp_path / 'b.md').write_text('# A title, here\n')
  p = tmp_path / 'x.md'
  p.write_text('![ok](a.png) [gone](nothing.json) [web](https://x.org/y) [ok](b.md#a-title-here)\n'
               '[no](b.md#other) [self](#top)\n```\nx[0](1)\n```\n# Top\n')
  assert _broken_links(str(p)) == ['nothing.json', 'b.md#other']


def test_every_relative_link_in_the_documents_resolves():
  docs = _documents()
  assert os.path.join(REPO, 'benchmarks', 'README.md') in docs
  bad = {os.path.relpath(p, REPO): links for p in docs if (links := _broken_links(p))}
  assert not bad, f'links to nothing: {bad}'


BENCHMARKS = os.path.join(REPO, 'benchmarks')
MAX_RESULT_FILES, MAX_RESULT_BYTES = 60, 8_000_000
SOURCES = ('.py', '.sh', '.patch')  # scripts and patches: not results


def _result_files(top: str = BENCHMARKS) -> list:
  """Every result file under ``top``: all files but scripts, patches and
  README.md (benchmarks/README.md, "What the folder may hold"); caches and
  hidden folders are not walked."""
  out = []
  for d, dirs, files in os.walk(top):
    dirs[:] = [x for x in dirs if x != '__pycache__' and not x.startswith('.')]
    out += [os.path.normpath(os.path.join(d, f)) for f in files
            if not f.endswith(SOURCES) and f != 'README.md' and not f.startswith('.')]
  return sorted(out)


def test_the_result_file_count_sees_what_it_should(tmp_path):
  for name in ('a.py', 'b.sh', 'c.patch', 'README.md', 'results/d.json', 'results/e.png',
               'research/x/results/f.jsonl', 'research/x/README.md', '__pycache__/g.pyc',
               'research/x/results/study.md'):
    (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / name).write_text('x')
  assert [os.path.relpath(p, tmp_path) for p in _result_files(str(tmp_path))] == [
      'research/x/results/f.jsonl', 'research/x/results/study.md', 'results/d.json',
      'results/e.png']


def test_the_benchmark_results_stay_within_60_files_and_8_mb():
  """The record stays a record: a result a later one replaces leaves the
  tree (git history holds it) rather than piling up beside it."""
  files = _result_files()
  size = sum(os.path.getsize(p) for p in files)
  assert len(files) >= 20  # the walk finds them
  assert len(files) <= MAX_RESULT_FILES, (
      f'{len(files)} result files under benchmarks/ (at most {MAX_RESULT_FILES}): retire what a '
      'later result replaced')
  assert size <= MAX_RESULT_BYTES, f'{size / 1e6:.2f} MB of results (at most 8 MB)'


def _linked_files(path: str) -> set:
  """Absolute paths of the files a Markdown file links (links and images,
  not code spans)."""
  text = re.sub(r'```.*?```', '', open(path).read(), flags=re.S)
  text = re.sub(r'`[^`\n]*`', '', text)
  out = set()
  for target in re.findall(r'\]\(([^)\s]+)\)', text):
    file = target.partition('#')[0]
    if file and not re.match(r'[a-z]+:', target):
      out.add(os.path.normpath(os.path.join(os.path.dirname(path), file)))
  return out


def test_every_result_file_is_cited_by_a_document():
  """A result file nobody links is a result nobody reads: link it where its
  topic lives, or leave it to git history. A report's data (NAME.json beside
  a linked NAME.md) counts as cited with it."""
  linked = set().union(*(_linked_files(p) for p in _documents()))
  assert os.path.normpath(os.path.join(BENCHMARKS, 'results', 'study.md')) in linked
  uncited = [os.path.relpath(p, REPO) for p in _result_files()
             if p not in linked
             and not (p.endswith('.json') and p[:-len('json')] + 'md' in linked)]
  assert not uncited, f'result files no document links: {uncited}'


RESEARCH_README_FIRST_PAGE = 60  # lines


def _summary_problems(path: str) -> list:
  """What keeps a research README from opening with a one-page summary: a
  'Summary' heading within its first page, the section no longer than a
  page, and at least one link down to its dated log (a heading of the same
  file)."""
  lines = open(path).read().split('\n')
  page = lines[:RESEARCH_README_FIRST_PAGE]
  heads = [i for i, l in enumerate(page) if re.match(r'#{1,3} +Summary\b', l, re.I)]
  if not heads:
    return [f'no "## Summary" heading in its first {RESEARCH_README_FIRST_PAGE} lines']
  start = heads[0]
  end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith('#')), len(lines))
  problems = []
  if end - start > RESEARCH_README_FIRST_PAGE:
    problems.append(f'the summary runs {end - start} lines (a page: '
                    f'{RESEARCH_README_FIRST_PAGE})')
  anchors = _anchors(path)
  links = re.findall(r'\]\(#([^)\s]+)\)', '\n'.join(lines[start:end]))
  if not any(a in anchors for a in links):
    problems.append('the summary links to no section of the log below it')
  return problems


def test_the_summary_check_sees_what_is_missing(tmp_path):
  p = tmp_path / 'README.md'
  p.write_text('# R\n\n## Log (2026-11-26)\n\ntext\n')
  assert _summary_problems(str(p)) == ['no "## Summary" heading in its first 60 lines']
  p.write_text('# R\n\n## Summary\n\n' + 'line\n' * 70 + '## Log (2026-11-26)\n')
  assert _summary_problems(str(p)) == ['the summary runs 72 lines (a page: 60)',
                                       'the summary links to no section of the log below it']
  p.write_text('# R\n\n## Summary\n\nWon: [this](#log-2026-11-26).\n\n## Log (2026-11-26)\n')
  assert _summary_problems(str(p)) == []


def test_every_research_readme_opens_with_a_one_page_summary():
  readmes = sorted(os.path.join(RESEARCH, d, 'README.md') for d in os.listdir(RESEARCH)
                   if os.path.isdir(os.path.join(RESEARCH, d)))
  assert len(readmes) >= 4 and all(os.path.isfile(p) for p in readmes), readmes
  bad = {os.path.relpath(p, REPO): problems for p in readmes
         if (problems := _summary_problems(p))}
  assert not bad, bad


# A commit hash: 7 to 40 hex digits with a letter and a digit among them.
COMMIT = re.compile(r'\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b')


def test_the_commit_check_sees_hashes():
  assert COMMIT.findall("commit f597033 is the last; 0x1f 'deadbeef' 1234567 dusty1_0025000000") \
      == ['f597033']


def test_the_library_names_no_commit():
  """What the library reads and refuses is said in its own terms (a field,
  a version), not by a commit of its history: those belong to the record."""
  bad = {os.path.relpath(p, REPO): COMMIT.findall(open(p).read())
         for p in _python_files('dusty_jax') if COMMIT.search(open(p).read())}
  assert not bad, f'commit hashes in the library: {bad}'
