"""deploy/: the compose files are well-formed (YAML, services, healthcheck, dependencies, ports bound to
the host's loopback), every command in them is a valid `uavmm` invocation (parsed by the real CLI and
turned into the real settings), and every file the Dockerfile copies exists. No Docker engine needed."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import yaml

from uavmm.cli import build_parser

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"
COMPOSE_FILES = ["docker-compose.yml", "docker-compose.router.yml"]
SECURE = "docker-compose.secure.yml"
SHARDED = "docker-compose.sharded.yml"
ALL_COMPOSE_FILES = [*COMPOSE_FILES, SECURE]
SHARDS = ["shard0", "shard1"]
AGENTS = ["uav1", "uav2", "uav3"]
_VARIABLE = re.compile(r"\$\{(\w+)(?::?-([^}]*))?\}")


def env_example() -> dict[str, str]:
    """KEY=VALUE lines of deploy/.env.example."""
    values = {}
    for line in (DEPLOY / ".env.example").read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            key, value = line.split("=", 1)
            values[key.strip()] = value.strip()
    return values


def interpolate(value, env: dict[str, str], used: set[str]):
    """Compose-style ${VAR}, ${VAR:-default} substitution, recursively through lists and maps."""
    if isinstance(value, str):
        def sub(match: re.Match) -> str:
            used.add(match.group(1))
            if match.group(1) in env:
                return env[match.group(1)]
            assert match.group(2) is not None, f"${{{match.group(1)}}} has no default"
            return match.group(2)
        return _VARIABLE.sub(sub, value)
    if isinstance(value, list):
        return [interpolate(v, env, used) for v in value]
    if isinstance(value, dict):
        return {k: interpolate(v, env, used) for k, v in value.items()}
    return value


def load(name: str, env: dict[str, str] | None = None) -> dict:
    """A compose file with its variables at their defaults (or `env`)."""
    raw = yaml.safe_load((DEPLOY / name).read_text())  # resolves the x-* anchors and << merges
    return interpolate(raw, env or {}, set())


def flag(command: list[str], name: str) -> str:
    return command[command.index(name) + 1]


def parse(command: list[str]):
    """Parse a container command with the real CLI (the image's entrypoint is `uavmm`)."""
    assert all(isinstance(a, str) for a in command), command
    try:
        return build_parser().parse_args(command)
    except SystemExit as exc:
        raise AssertionError(f"not a valid uavmm command line: uavmm {shlex.join(command)}") from exc


@pytest.mark.parametrize("name", COMPOSE_FILES)
def test_every_compose_command_is_a_valid_uavmm_invocation(name):
    from uavmm import cmd_agent, cmd_fusion

    services = load(name)["services"]
    for service, spec in services.items():
        if not spec.get("image", "").startswith("uavmm:"):
            continue
        args = parse(spec["command"])
        if args.command == "fusion":
            settings = cmd_fusion.settings_from_args(args)  # the values, not only the flags
            assert (settings.http_host, settings.http_port) == ("0.0.0.0", 8000)
            # published on the host's loopback only: the demo's API is open on purpose, and says so
            assert settings.insecure_public and not settings.http_tokens
            assert str(settings.db_path) == "/data/fusion.sqlite"
        else:
            assert args.command == "agent", service
            settings = cmd_agent.settings_from_args(args)
            source = cmd_agent.source_from_args(args)  # the scenario and UAV index exist
            assert settings.uav_id == service and source.video.uav == service
            assert args.loop, "demo agents fly until stopped"


@pytest.mark.parametrize("name", ALL_COMPOSE_FILES)
def test_compose_demo_has_fusion_and_three_agents_on_one_scenario(name):
    services = load(name)["services"]
    assert {"fusion", *AGENTS} <= set(services)
    fusion = services["fusion"]
    assert fusion["build"] == {"context": "..", "dockerfile": "deploy/Dockerfile"}
    assert (DEPLOY / fusion["build"]["context"] / fusion["build"]["dockerfile"]).is_file()
    commands = [services[a]["command"] for a in AGENTS]
    assert sorted(flag(c, "--uav-index") for c in commands) == ["0", "1", "2"]
    assert len({(flag(c, "--sim"), flag(c, "--seed")) for c in commands}) == 1  # one shared world
    for agent in AGENTS:
        spec = services[agent]
        assert spec["image"] == fusion["image"], "agents and fusion run one image"
        assert spec["depends_on"] == {"fusion": {"condition": "service_healthy"}}
        assert "ports" not in spec, "agents publish nothing on the host"


@pytest.mark.parametrize("name", ALL_COMPOSE_FILES)
def test_fusion_healthcheck_asks_healthz(name):
    check = load(name)["services"]["fusion"]["healthcheck"]
    test = check["test"]
    assert test[0] == "CMD" and "http://127.0.0.1:8000/healthz" in " ".join(test)
    assert check["retries"] >= 1 and check["interval"].endswith("s")


@pytest.mark.parametrize("name", [*ALL_COMPOSE_FILES, SHARDED])
def test_ports_are_published_on_the_hosts_loopback_only(name):
    services = load(name)["services"]
    published = [p for spec in services.values() for p in spec.get("ports", [])]
    assert published
    for mapping in published:
        assert mapping.startswith("127.0.0.1:"), f"{mapping} is reachable from other hosts by default"
    rest = "gateway" if name == SHARDED else "fusion"
    assert "127.0.0.1:8000:8000" in services[rest]["ports"]


def test_agents_connect_to_the_fusion_server_directly():
    services = load("docker-compose.yml")["services"]
    assert flag(services["fusion"]["command"], "--listen") == "tcp/0.0.0.0:7447"
    for agent in AGENTS:
        assert flag(services[agent]["command"], "--connect") == "tcp/fusion:7447"


def test_router_variant_puts_zenohd_between_fusion_and_agents():
    services = load("docker-compose.router.yml")["services"]
    router = services["router"]
    assert router["image"].startswith("eclipse/zenoh:")  # the official zenohd image
    assert "--no-multicast-scouting" in router["command"]
    assert flag(router["command"], "--listen") == "tcp/0.0.0.0:7447"
    fusion = services["fusion"]["command"]
    assert services["fusion"]["depends_on"] == {"router": {"condition": "service_started"}}
    # all clients of the router: it forwards between clients, not between peers (see the compose file)
    for command in [fusion] + [services[a]["command"] for a in AGENTS]:
        assert flag(command, "--mode") == "client" and flag(command, "--connect") == "tcp/router:7447"


@pytest.mark.parametrize("name", [*ALL_COMPOSE_FILES, SHARDED])
def test_compose_variables_are_documented_in_env_example_with_the_same_defaults(name):
    env = env_example()
    used: set[str] = set()
    raw = yaml.safe_load((DEPLOY / name).read_text())
    with_defaults = interpolate(raw, {}, used)
    assert used <= set(env), f"undocumented variables: {sorted(used - set(env))}"
    assert interpolate(raw, env, set()) == with_defaults, ".env.example and the compose defaults disagree"


def test_sharded_variant_runs_two_shards_and_a_gateway_behind_zenohd():
    """The commands of docker-compose.sharded.yml through the real CLI and their settings: two shards of
    one count and region zoom, each with its own database volume; everyone a Zenoh client of the
    official router."""
    from uavmm import cmd_agent, cmd_fusion

    services = load(SHARDED)["services"]
    assert {"router", "gateway", *SHARDS, *AGENTS, "uav4"} == set(services)
    router = services["router"]
    assert router["image"].startswith("eclipse/zenoh:") and flag(router["command"], "--listen") == "tcp/0.0.0.0:7447"
    shard_settings = []
    for name in SHARDS:
        spec = services[name]
        args = parse(spec["command"])
        assert args.command == "fusion"
        settings = cmd_fusion.settings_from_args(args)
        shard_settings.append(settings)
        assert str(settings.db_path) == "/data/fusion.sqlite"
        assert not settings.zenoh.listen, "a client of the router opens no listener"
        assert spec["volumes"] == [f"{name}-data:/data"], "each shard keeps its own database"
        # its REST API on the container's loopback only: the health check's, not the operators'
        assert (settings.http_host, settings.http_port) == ("127.0.0.1", 8000) and not settings.insecure_public
        assert "ports" not in spec
    assert sorted((s.shard_index, s.shard_count) for s in shard_settings) == [(0, 2), (1, 2)]
    assert services["shard0"]["build"] == {"context": "..", "dockerfile": "deploy/Dockerfile"}
    assert "build" not in services["shard1"] and services["shard1"]["pull_policy"] == "never"
    assert set(load(SHARDED).get("volumes", {})) == {"shard0-data", "shard1-data"}
    for name in ["gateway", *SHARDS]:
        test = " ".join(services[name]["healthcheck"]["test"])
        assert "http://127.0.0.1:8000/healthz" in test
    for name in [*SHARDS, "gateway", *AGENTS, "uav4"]:
        command = services[name]["command"]
        assert flag(command, "--mode") == "client" and flag(command, "--connect") == "tcp/router:7447", name
        assert "--no-multicast-scouting" in command
    for name in [*AGENTS, "uav4"]:
        spec = services[name]
        args = parse(spec["command"])
        assert cmd_agent.settings_from_args(args).uav_id == name
        cmd_agent.source_from_args(args)  # the scenario and UAV index exist
        assert args.loop and spec["depends_on"] == {"gateway": {"condition": "service_healthy"}}
        assert spec["image"] == services["shard0"]["image"] and "ports" not in spec


def test_sharded_gateway_serves_both_shards_on_the_hosts_loopback():
    """The gateway's command through the real CLI: as many shards as the compose file runs, at their
    region zoom, its REST API on the container's 0.0.0.0 published on the host's loopback."""
    from uavmm import cmd_fusion, cmd_gateway

    services = load(SHARDED)["services"]
    shard_settings = [cmd_fusion.settings_from_args(parse(services[name]["command"])) for name in SHARDS]
    gateway_spec = services["gateway"]
    gateway_args = parse(gateway_spec["command"])
    assert gateway_args.command == "gateway"
    gateway = cmd_gateway.settings_from_args(gateway_args)
    assert gateway.shard_count == 2 and gateway.db_path is None
    assert {s.region_zoom for s in shard_settings} == {gateway.region_zoom}, "shards and gateway must agree"
    assert (gateway.http_host, gateway.http_port) == ("0.0.0.0", 8000) and gateway.insecure_public
    assert gateway_spec["depends_on"] == {s: {"condition": "service_healthy"} for s in SHARDS}


def test_sharded_demo_gives_each_shard_a_meadow():
    """The demo's agents fly over regions of both shards at the compose file's region zoom (its header
    says so): the trio meadow is shard 0's, the second scenario's shard 1's."""
    from shared.sharding import ShardSpec
    from shared.tiles import TileGrid
    from sim.scenarios import get_scenario

    services = load(SHARDED)["services"]
    zoom = int(flag(services["shard0"]["command"], "--region-zoom"))
    grid = TileGrid()
    owners = {}
    for agent in ["uav1", "uav4"]:
        world = get_scenario(flag(services[agent]["command"], "--sim")).world
        x, y = grid.tile_of(np.array([world.origin_lat]), np.array([world.origin_lon]))
        owners[agent] = ShardSpec(0, 2, zoom).owner(grid.z, int(x[0]), int(y[0]))
    assert owners == {"uav1": 0, "uav4": 1}


def test_secure_variant_runs_on_the_files_secure_init_writes(tmp_path):
    """Run the command its header gives, then check every service's command against the folder it mounts."""
    from fusion_server.http_auth import read_token_file
    from shared.pki import certificate_common_name
    from uavmm import cmd_agent, cmd_fusion
    from uavmm.cli import main

    header = (DEPLOY / SECURE).read_text().split("\n#   uavmm secure init ", 1)[1].split("\n#   sudo", 1)[0]
    init_args = shlex.split(header.replace("\\\n#", " "))
    secrets = tmp_path / "secrets"
    assert init_args[0] == "deploy/secrets"
    assert main(["secure", "init", str(secrets), *init_args[1:]]) == 0
    services = load(SECURE)["services"]
    for name, spec in services.items():
        mounts = [v for v in spec["volumes"] if v.endswith(":/etc/uavmm:ro")]
        assert len(mounts) == 1, f"{name} mounts exactly its own folder, read-only"
        folder = secrets / mounts[0].split(":")[0].removeprefix("./secrets/")
        assert folder.is_dir(), f"{name}: {folder} is not written by uavmm secure init"
        local = [part.replace("/etc/uavmm", str(folder)) for part in spec["command"]]
        args = parse(local)
        config = json.loads("".join(line for line in (folder / "zenoh.json5").read_text().splitlines()
                                    if not line.startswith("//")))
        tls = config["transport"]["link"]["tls"]
        assert all(path.startswith("/etc/uavmm/") for key, path in tls.items() if key != "enable_mtls")
        assert tls["enable_mtls"] is True
        if args.command == "fusion":
            settings = cmd_fusion.settings_from_args(args)
            assert settings.http_tokens == read_token_file(folder / "http-tokens") and not settings.insecure_public
            assert config["mode"] == "router" and config["access_control"]["default_permission"] == "deny"
            assert config["listen"]["endpoints"] == ["tls/0.0.0.0:7447"]
        else:
            settings = cmd_agent.settings_from_args(args)
            assert settings.uav_id == name
            assert certificate_common_name((folder / "cert.pem").read_bytes()) == name
            assert config["mode"] == "client" and config["connect"]["endpoints"] == ["tls/fusion:7447"]


def test_settings_from_env_example_are_valid_too():
    env = {**env_example(), "UAVMM_SCENARIO": "coop"}
    services = load("docker-compose.yml", env)["services"]
    # coop has two UAVs: the third agent's index is out of range, which the CLI reports clearly
    parse(services["uav1"]["command"])
    from uavmm import cmd_agent

    with pytest.raises(ValueError, match="uav_index must be in 0..1"):
        cmd_agent.source_from_args(parse(services["uav3"]["command"]))


def dockerfile_instructions() -> list[tuple[str, str]]:
    text = (DEPLOY / "Dockerfile").read_text().replace("\\\n", " ")
    rows = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            keyword, _, rest = line.partition(" ")
            rows.append((keyword.upper(), rest.strip()))
    return rows


def test_dockerfile_copies_files_that_exist_and_every_package():
    rows = dockerfile_instructions()
    assert rows[0] == ("FROM", "python:3.11-slim")
    copied = []
    for keyword, rest in rows:
        if keyword == "COPY":
            *sources, _dest = rest.split()
            for source in sources:
                assert (REPO / source).exists(), f"COPY {source}: not in the build context (the repo root)"
                copied.append(source)
    find_section = (REPO / "pyproject.toml").read_text().split("[tool.setuptools.packages.find]")[1].split("\n\n")[0]
    packages = re.findall(r'"(\w+)\*"', find_section)
    assert packages and set(packages) <= set(copied), f"packages not copied: {set(packages) - set(copied)}"
    assert {"pyproject.toml", "README.md", "requirements-nodeps.txt"} <= set(copied)


def dockerfile_extras() -> set[str]:
    """The extras of the Dockerfile's `pip install .[...]` of the package (AssertionError if it installs none)."""
    run = " ".join(rest for keyword, rest in dockerfile_instructions() if keyword == "RUN")
    match = re.search(r"""pip install ["']?\.(?:\[([\w,-]+)\])?["']?(?:\s|$)""", run)
    assert match, "the Dockerfile does not pip install the package (.)"
    return set(match.group(1).split(",")) if match.group(1) else set()


def requirement_names(requirements: list[str]) -> set[str]:
    return {re.match(r"[A-Za-z0-9_.-]+", r).group(0).lower().replace("-", "_") for r in requirements}


def test_the_image_has_what_its_commands_import():
    """The image is for every process (docs/deploy.md): `agent` with live MAVLink / PX4 telemetry (the agent
    extra) and `eval`'s baselines, which it installs with --no-deps (their runtime imports: the eval extra).
    Run with the packages the image leaves out made unimportable: it used to install norfair without rich and
    filterpy (`uavmm eval --tasks tracking` failed in the image) and no pymavlink or pyulog."""
    import subprocess
    import sys

    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    installed = dockerfile_extras()
    assert installed <= set(extras), f"the Dockerfile names extras pyproject does not have: {installed - set(extras)}"
    in_image = requirement_names(project["dependencies"] + [r for e in installed for r in extras[e]])
    in_image |= requirement_names([ln.split("#")[0].strip() for ln in (REPO / "requirements-nodeps.txt").read_text()
                                   .splitlines() if ln.split("#")[0].strip()])
    left_out = requirement_names([r for role in ("agent", "eval") for r in extras[role]]) - in_image
    code = (f"import sys\nfor name in {sorted(left_out)!r}:\n    sys.modules[name] = None\n"
            "import norfair, trackeval\nfrom pymavlink.dialects.v20 import ardupilotmega\nfrom pyulog import ULog\n")
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f"without {sorted(left_out)} (not in the image):\n{result.stderr[-800:]}"


def test_dockerfile_installs_like_the_makefile_and_runs_unprivileged():
    rows = dockerfile_instructions()
    run = " ".join(rest for keyword, rest in rows if keyword == "RUN")
    dockerfile_extras()  # the package itself
    assert "pip install --no-deps -r requirements-nodeps.txt" in run
    assert "--no-deps -r requirements-nodeps.txt" in (REPO / "Makefile").read_text()  # the same file, the same way
    users = [rest for keyword, rest in rows if keyword == "USER"]
    assert users and users[-1] not in ("root", "0")
    assert ("ENTRYPOINT", '["uavmm"]') in rows
    ignore = (DEPLOY / "Dockerfile.dockerignore").read_text().split()
    assert {".git", ".venv"} <= set(ignore)


def test_the_role_extras_are_covered_by_the_test_extra_ci_installs():
    """What `.[agent]`, `.[eval]` and `.[dev]` promise is installed and exercised by CI (`.[test]`)."""
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert {"agent", "server", "eval", "dev", "test"} <= set(extras)
    test = set(extras["test"])
    for role in ("agent", "eval", "dev"):
        assert set(extras[role]) <= test, f"{role} extra not in test: {set(extras[role]) - test}"
