"""
The documentation: the site builds without a warning, the README stays short, the tutorials run.

- The Sphinx site (``docs/``, ``make docs``) is built with warnings as errors; its generated
  tables must hold every setting, every node parameter, every message and every verb.
- The README is at most 150 lines, starts with its two commands and links only files that exist.
- Every tutorial page (``docs/tutorials/*.md``) is run: its ``bash`` code blocks, in order, as
  one script from the repository root (``set -euo pipefail``), so a changed command fails here.
  Blocks fenced as ``shell`` are shown, not run (e.g. ``ros2 launch`` on a full ROS install).
  A tutorial writes only under ``out/tutorials/<page>/``, removed before its run. The OU44
  data and the BOPTEST test case reach a page as ``$OU44_CSV`` and ``$MSHOOT_BOPTEST_DIR``
  (the ``ou44_csv`` and ``boptest_case`` fixtures: skipped when absent, failed under CI).
"""
import os
import pathlib
import random
import re
import shutil
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / 'docs'
TUTORIALS = sorted((DOCS / 'tutorials').glob('*.md'))
#: A fenced block of a Markdown page: its info string and its text.
FENCE = re.compile(r'^(`{3,})([^\n`]*)\n(.*?)^\1[ \t]*$', re.M | re.S)
#: Deadlock guard of one tutorial [s] (wall time); the pages take seconds to a minute.
TUTORIAL_GUARD_S = 900


def code_blocks(text: str, language: str) -> list[str]:
    """Return the fenced code blocks of ``text`` whose info string is ``language``."""
    return [body for _, info, body in FENCE.findall(text) if info.strip() == language]


def test_code_blocks_are_found() -> None:
    text = ('intro\n```bash\necho one\n```\n````md\n```bash\nnested\n```\n````\n'
            '```shell\nros2 launch x\n```\n```bash\necho two\n```\n')
    assert code_blocks(text, 'bash') == ['echo one\n', 'echo two\n']
    assert code_blocks(text, 'shell') == ['ros2 launch x\n']


@pytest.fixture(scope='module')
def site(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    """Build the site as ``make docs`` does (warnings as errors) into a fresh folder."""
    out = tmp_path_factory.mktemp('docs')
    done = subprocess.run(
        [sys.executable, '-m', 'sphinx', '-W', '--keep-going', '-q', '-b', 'html',
         '-d', str(out / 'doctrees'), str(DOCS), str(out / 'html')],
        capture_output=True, text=True, cwd=ROOT, timeout=900, check=False)
    assert done.returncode == 0, f'sphinx-build failed:\n{done.stderr}{done.stdout}'
    assert 'WARNING' not in done.stderr, done.stderr
    return out / 'html'


def _text(html: pathlib.Path) -> str:
    """Return the text of an HTML page, tags dropped and entities of names undone."""
    text = re.sub(r'<[^>]+>', '', html.read_text(encoding='utf-8'))
    return text.replace('&#8211;', '-').replace('&#8212;', '-').replace('&quot;', '"')


def test_site_has_every_setting(site: pathlib.Path) -> None:
    from mshoot_core.models.registry import MODEL_PARAMETERS
    from mshoot_core.settings import PARAMETERS
    page = _text(site / 'concepts' / 'settings.html')
    missing = [f.name for f in (*PARAMETERS, *MODEL_PARAMETERS) if f.name not in page]
    assert not missing
    from mshoot_studies.case import CASE_SETTINGS
    for f in PARAMETERS:
        if f.name in CASE_SETTINGS:
            assert (f.cli or '--' + f.name.replace('_', '-')) in page


def test_site_has_every_node_parameter_topic_and_message(site: pathlib.Path) -> None:
    import importlib
    page = _text(site / 'reference' / 'ros.html')
    for module in ('emulator_node', 'forecaster_node', 'mpc_node', 'recorder_node',
                   'replayer_node'):
        specs = importlib.import_module(f'mshoot_nodes.{module}').PARAMS
        missing = [spec.name for spec in specs if spec.name not in page]
        assert not missing, module
    from mshoot_nodes import contract
    assert all(topic in page for topic in contract.TOPIC_TYPES)
    for msg in (ROOT / 'ros2_ws/src/mshoot_msgs/msg').glob('*.msg'):
        assert f'mshoot_msgs/msg/{msg.stem}' in page
        # the definition itself, e.g. its last field
        last = [line for line in msg.read_text().splitlines() if line and line[0] != '#'][-1]
        assert last.split()[-1] in page


def test_site_has_every_verb_help(site: pathlib.Path) -> None:
    from mshoot_studies.cli import VERBS
    page = _text(site / 'reference' / 'cli.html')
    for verb in VERBS:
        assert f'usage: mshoot {verb}' in page
    assert 'usage: bringup' in page


def test_readme_is_short_and_starts_with_the_two_commands() -> None:
    lines = (ROOT / 'README.md').read_text(encoding='utf-8').splitlines()
    assert len(lines) <= 150
    first = code_blocks('\n'.join(lines) + '\n', 'bash')[0].splitlines()
    assert first[0].startswith('make demo') and first[1].startswith('make test')
    assert not any(line.startswith('```') for line in lines[:lines.index('```bash')])


def test_readme_links_reach_files_that_exist() -> None:
    # the site's build checks the links of docs/, not those of the README (outside the site)
    text = (ROOT / 'README.md').read_text(encoding='utf-8')
    links = [link.partition('#')[0] for link in re.findall(r'\]\(([^)\s]+)\)', text)
             if not link.startswith(('http://', 'https://', '#'))]
    assert links, 'the README links no page'
    missing = [link for link in links if not (ROOT / link).exists()]
    assert not missing, f'README links to missing files: {missing}'


@pytest.mark.host_discovery
@pytest.mark.parametrize('page', TUTORIALS, ids=[p.stem for p in TUTORIALS])
def test_tutorial_runs(page: pathlib.Path, request: pytest.FixtureRequest) -> None:
    text = page.read_text(encoding='utf-8')
    blocks = code_blocks(text, 'bash')
    assert blocks, f'{page.name} has no bash block to run'
    # the processes of a tutorial find each other as a user's do: discovery on this host, a
    # domain of its own (other tests of this session turn discovery OFF in os.environ)
    env = {**os.environ, 'ROS_DOMAIN_ID': str(random.randint(1, 100)),
           'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST', 'PYTHONUNBUFFERED': '1'}
    if 'OU44_CSV' in text:
        env['OU44_CSV'] = str(request.getfixturevalue('ou44_csv'))
    if 'MSHOOT_BOPTEST_DIR' in text:
        env['MSHOOT_BOPTEST_DIR'] = str(request.getfixturevalue('boptest_case').directory)
    out = ROOT / 'out' / 'tutorials' / page.stem
    shutil.rmtree(out, ignore_errors=True)
    script = 'set -euo pipefail\n' + '\n'.join(
        f'echo "### block {i}" >&2\n{block}' for i, block in enumerate(blocks, 1))
    done = subprocess.run(['bash', '-c', script], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=TUTORIAL_GUARD_S, check=False)
    assert done.returncode == 0, (f'{page.name}: exit {done.returncode}\n'
                                  f'--- stdout\n{done.stdout[-4000:]}\n'
                                  f'--- stderr\n{done.stderr[-4000:]}')
