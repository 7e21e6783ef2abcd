"""The architecture a newcomer can change: one home per contract fact, and stages that only import downwards."""

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "vla_ladder"
CONTRACT_NAMES = ("ENV_ID", "EPISODE_STEPS", "SIM_HZ", "CONTROL_HZ", "CAMERAS", "CAMERA_NAMES", "CAMERA_KEYS",
                  "IMAGE_SHAPE", "STATE_DIM", "STATE_NAMES", "ACTION_DIM", "ACTION_NAMES", "STATE_KEY",
                  "ACTION_KEY", "METRICS", "RANK_BY", "INFO_KEYS", "REACH_THRESHOLD", "REGIMES", "SPLITS")


def _assignments() -> dict[str, list[str]]:
    """Module-level names bound by an assignment, -> the files that bind them."""
    found: dict[str, list[str]] = {}
    for path in SRC.rglob("*.py"):
        for node in ast.parse(path.read_text()).body:
            targets = node.targets if isinstance(node, ast.Assign) else \
                [node.target] if isinstance(node, ast.AnnAssign) else []
            for t in targets:
                for name in ([t] if isinstance(t, ast.Name) else getattr(t, "elts", [])):
                    if isinstance(name, ast.Name):
                        found.setdefault(name.id, []).append(str(path.relative_to(SRC)))
    return found


def test_every_contract_fact_has_one_home():
    found = _assignments()
    for name in CONTRACT_NAMES:
        assert len(found.get(name, [])) == 1, f"{name} is defined in {found.get(name)}"


def test_lerobot_feature_keys_are_never_typed_out():
    """observation.state, observation.images.* and the action key are LeRobot's constants, spelt once: in the
    contract, which imports neither LeRobot nor torch (lerobot.utils imports torch: 1.2 s before every command's
    --help or one-line refusal), and every stage reads them from there."""
    from lerobot.utils import constants

    from vla_ladder import contract

    assert (contract.ACTION, contract.OBS_IMAGES, contract.OBS_STATE) == \
        (constants.ACTION, constants.OBS_IMAGES, constants.OBS_STATE)
    pattern = re.compile(r"""["']observation\.(state|images\.[a-z_]+)["']""")
    offenders = [str(p.relative_to(SRC)) for p in SRC.rglob("*.py")
                 if p.name != "contract.py" and pattern.search(p.read_text())]
    assert offenders == []
    code = ("import sys, vla_ladder.contract; "
            "print(sorted({'torch', 'lerobot'} & {m.split('.')[0] for m in sys.modules}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("config", ["evaluation.runner", "recording.record", "recording.server",
                                    "experiments.study", "experiments.probes", "experiments.diagnose",
                                    "evaluation.compare", "report.placements", "training.check_dataset"])
def test_a_command_line_is_checked_without_torch(config):
    """These commands' configs refuse a bad input before any work; their modules import no torch (1.2 s), which
    the policies, the simulator and the models bring when the work starts (`eval --help` took 3.0 s, now 1.6)."""
    code = f"import sys, vla_ladder.{config}; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_stages_import_only_downwards():
    """The layers contract in pyproject.toml (import-linter): cli > experiments > report > the stages
    (evaluation, training, recording, ppo, lerobot_env; siblings never import each other) > policies > task >
    the ground floor (contract, conditions, files, stats, recordings, commandline, machine, checks)."""
    lint = Path(sys.executable).with_name("lint-imports")
    r = subprocess.run([str(lint), "--no-cache"], capture_output=True, text=True, cwd=SRC.parents[1])
    assert r.returncode == 0, r.stdout[-3000:]
    assert "1 kept, 0 broken" in r.stdout


@pytest.mark.slow
@pytest.mark.parametrize("module", ["vla_ladder.contract", "vla_ladder.conditions", "vla_ladder.task.layouts",
                                    "vla_ladder.recordings"])
def test_the_ground_floor_is_simulator_free(module):
    code = f"import sys, {module}; print(any(m.startswith(('mani_skill', 'sapien')) for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_the_architecture_page_names_every_module_under_its_package():
    """docs/architecture.md's tree is the map a newcomer reads first: a module missing from it is one they cannot
    find (the review of 2026-11-27 found eleven missing). Each module's name must appear in its package's lines."""
    doc = (SRC.parents[1] / "docs" / "architecture.md").read_text()
    tree = doc[doc.index("```\nsrc/vla_ladder/"):]
    tree = tree[:tree.index("```\n", 4)]
    blocks: dict[str, str] = {}  # package -> its lines in the tree (a package line and its continuations)
    current = "ground floor"
    for line in tree.splitlines()[1:]:
        head = line.split()[0] if line.strip() and not line.startswith(" " * 6) else None
        if head:
            current = "ground floor" if head == "ground" else head.rstrip("/")
        blocks[current] = blocks.get(current, "") + line + "\n"
    missing = []
    for path in sorted(SRC.rglob("*.py")):
        package = path.parent.name if path.parent != SRC else ("cli" if path.stem == "cli" else "ground floor")
        if path.name != "__init__.py" and path.name not in blocks.get(package if package != "cli" else "cli.py", ""):
            missing.append(str(path.relative_to(SRC)))
    assert missing == [], f"docs/architecture.md's tree does not name {missing}"


def test_every_policy_flag_help_lists_every_policy_kind():
    """The recipe for a policy kind names these help texts; diagnose's lacked `committed`."""
    import inspect
    import re

    from vla_ladder.evaluation.runner import EvalConfig
    from vla_ladder.experiments.diagnose import DiagnoseConfig
    from vla_ladder.experiments.probes import ProbeConfig
    from vla_ladder.policies import POLICY_KINDS

    for cls in (EvalConfig, ProbeConfig, DiagnoseConfig):
        help_text = re.search(r"\n    policy: [^\n]*\n    \"\"\"(.*?)\"\"\"", inspect.getsource(cls), re.S).group(1)
        words = set(re.findall(r"[a-z][a-z-]*(?=[:,\s)]|$)", " ".join(help_text.split())))
        assert set(POLICY_KINDS) <= words, (cls.__name__, sorted(set(POLICY_KINDS) - words))


def test_a_reference_kind_registered_once_is_a_reference_everywhere(tmp_path, monkeypatch):
    """The recipe for a policy kind: a kind without an argument, registered in POLICY_KINDS, is a reference that
    diagnose --references and a study's evaluation.reference_policies accept, and diagnose's help names it. Both
    kept their own list of the five (a newcomer's `still` kind was refused by both)."""
    import inspect

    from vla_ladder import policies
    from vla_ladder.experiments.diagnose import DiagnoseConfig
    from vla_ladder.experiments.study_config import EvaluationSpec

    monkeypatch.setitem(policies.POLICY_KINDS, "still", "vla_ladder.policies.reference:make_random")
    cfg = DiagnoseConfig(policy=("nearest",), out=tmp_path / "d", references=("still", "nearest"))
    assert [who for who, _, _ in cfg.plan()] == ["policy", "still", "nearest"]
    assert EvaluationSpec(reference_policies=["still"]).reference_policies == ["still"]
    with pytest.raises(ValueError, match="allowed: .*committed, still"):
        EvaluationSpec(reference_policies=["oracle"])
    monkeypatch.delitem(policies.POLICY_KINDS, "still")
    source = inspect.getsource(DiagnoseConfig)
    help_text = re.search(r"\n    references: .*?\n    \"\"\"(.*?)\"\"\"", source, re.S).group(1)
    references = [k for k in policies.POLICY_KINDS if k not in policies.NEEDS_ARG]
    assert all(kind in help_text for kind in references), help_text


# Module-level names that may spell the metrics out besides contract.py's (METRICS, and RANK_BY, the order models
# are ranked in): their titles.
METRIC_LISTS = {("report/tables.py", "METRIC_NAMES")}


def test_code_that_handles_every_metric_reads_contract_metrics():
    """The recipe for a metric: a list, tuple, set, dict or call's keywords that name every metric (success,
    grasp_any, reach) are contract.METRICS itself, or built from it. The episode columns, the player's rows, the
    recording protocol's header and provenance, and PPO's logs each spelt the three (PPO's training loop then
    failed on a fourth: KeyError), so a new metric needed edits in seven more modules; only the metrics' titles and
    the order models are ranked in name them now."""
    from vla_ladder.contract import METRICS

    spelt = []
    for path in sorted(SRC.rglob("*.py")):
        rel = str(path.relative_to(SRC))
        if rel in ("contract.py", "task/env.py"):  # where the metrics are named, and computed (evaluate())
            continue
        tree = ast.parse(path.read_text())
        bound = {id(node.value): t.id for node in tree.body if isinstance(node, (ast.Assign, ast.AnnAssign))
                 for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
                 if isinstance(t, ast.Name)}
        for node in ast.walk(tree):
            items = node.keys if isinstance(node, ast.Dict) else \
                node.elts if isinstance(node, (ast.Tuple, ast.List, ast.Set)) else []
            words = {e.value for e in items if isinstance(e, ast.Constant) and isinstance(e.value, str)}
            if isinstance(node, ast.Call):  # dict(success=..., grasp_any=..., reach=...)
                words = {k.arg for k in node.keywords}
            if set(METRICS) <= words and (rel, bound.get(id(node))) not in METRIC_LISTS:
                spelt.append(f"{rel}:{node.lineno}")
    assert spelt == [], f"these name every metric instead of reading contract.METRICS: {spelt}"


def test_every_relative_link_in_the_readme_and_docs_resolves():
    """The README's figures moved to docs/benchmarks.md, and other pages link to it and to each other: a page or
    heading renamed must not leave a newcomer a dead link. Checks the file and, for a .md target, the heading."""
    root = SRC.parents[1]

    def anchors(page: Path) -> set[str]:  # GitHub's heading ids: lower case, punctuation dropped, spaces to -
        text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
        return {re.sub(r"[^\w\- ]", "", re.sub(r"[`*_]", "", h.strip().lower())).replace(" ", "-")
                for h in re.findall(r"^#+\s+(.*)$", text, flags=re.M)}

    dead = []
    for page in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        text = re.sub(r"`[^`\n]*`", "", re.sub(r"```.*?```", "", page.read_text(), flags=re.S))
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
                continue
            file, _, heading = target.partition("#")
            dest = (page.parent / file) if file else page
            if not dest.exists() or (heading and dest.suffix == ".md" and heading not in anchors(dest)):
                dead.append(f"{page.relative_to(root)}: {target}")
    assert dead == [], f"dead links: {dead}"


def test_the_readme_lists_every_benchmark_script():
    """docs/benchmarks.md sends readers to the README's "Tests and benchmarks" table for what each script measures;
    four scripts were missing from it."""
    readme = (SRC.parents[1] / "README.md").read_text()
    scripts = sorted(p.name for p in (SRC.parents[1] / "benchmarks").glob("*.py") if not p.name.startswith("_"))
    assert scripts and [s for s in scripts if f"| `{s}" not in readme] == []

