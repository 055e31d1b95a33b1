"""The fleet's Zenoh access control: each identity may put, declare and ask only on its own keys.

Builds the ``access_control`` section of a Zenoh config (deny by default) for the node every link goes
through (the fusion server in router mode, or a zenohd router). Pure: no files, no Zenoh.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from shared.keys import KeySpace, validate_uav_id

__all__ = ["ACL_MESSAGES", "FUSION_IDENTITY", "MAX_IDENTITY_LEN", "ROUTER_IDENTITY", "FleetIdentities",
           "access_control"]

#: every message kind a Zenoh 1.x ACL rule can name
ACL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query")
#: the certificate common name / user name of the fusion server
FUSION_IDENTITY = "fusion"
#: the certificate common name of a zenohd router (its folder ``router/`` beside ``fusion/``)
ROUTER_IDENTITY = "router"
#: with client certificates an identity is a certificate's common name, which X.509 bounds to 64 characters
#: (RFC 5280, ub-common-name; `fusion_server.provision.FleetPlan` checks it in mtls mode)
MAX_IDENTITY_LEN = 64


@dataclass(frozen=True, slots=True)
class FleetIdentities:
    """Who may connect: the UAV ids and operator names (certificate CNs or usernames).

    uavs: UAV ids (the `--uav-id` of each agent; the safe id set of docs/protocol.md).
    operators: read-only identities (a ground-station viewer, a recorder).
    None is `FUSION_IDENTITY` or `ROUTER_IDENTITY` (the ground station's own identities: a UAV so named would get
    their folder and server certificate); with client certificates each is at most `MAX_IDENTITY_LEN` characters.
    """

    uavs: tuple[str, ...]
    operators: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.uavs:
            raise ValueError("uavs: give at least one UAV id")
        for group, members in (("uavs", self.uavs), ("operators", self.operators)):
            for name in members:
                validate_uav_id(name, group)  # operators too: the same safe characters, it becomes a file and a CN
        names = [*self.uavs, *self.operators, FUSION_IDENTITY, ROUTER_IDENTITY]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"identities must be unique (and not {FUSION_IDENTITY!r} or {ROUTER_IDENTITY!r}, the "
                             f"ground station's), repeated: {', '.join(duplicates)}")
        folded: dict[str, list[str]] = {}
        for name in names:
            folded.setdefault(name.casefold(), []).append(name)
        alike = sorted(" and ".join(group) for group in folded.values() if len(group) > 1)
        if alike:  # each identity is a folder (uavs/ID): one folder on a case-insensitive file system
            raise ValueError(f"identities must differ in more than case (each is a folder of the fleet, one on the "
                             f"case-insensitive file systems of macOS and Windows): {'; '.join(alike)}")


def _rule(rule_id: str, messages: Sequence[str], flow: str, key_exprs: Sequence[str]) -> dict[str, Any]:
    return {"id": rule_id, "messages": list(messages), "flows": [flow], "permission": "allow",
            "key_exprs": list(key_exprs)}


def access_control(identities: FleetIdentities, *, prefix: str = "uavmm/v1",
                   subject_field: str = "cert_common_names") -> dict[str, Any]:
    """The ``access_control`` config section for the fleet (Zenoh 1.x schema), deny by default.

    A UAV ``K`` may put and delete only under ``{prefix}/uav/K/**`` and declare only its own liveliness
    token; it may subscribe to the joint and region keys and to the other UAVs' state (its joint detections
    use their footprints), query the joint and region keys and watch the fusion shards' liveliness
    tokens (to route its tiles to their shard). The fusion identity may do anything under
    the prefix (it alone puts on ``{prefix}/joint/**`` and ``{prefix}/region/**``); operators may only
    subscribe and query. Everything else, and every other identity, is denied: their messages never reach
    the server.

    subject_field: ``cert_common_names`` (mutual TLS) or ``usernames`` (usrpwd).
    """
    if subject_field not in ("cert_common_names", "usernames"):
        raise ValueError(f"subject_field must be cert_common_names or usernames, got {subject_field!r}")
    keys = KeySpace(prefix)  # raises ValueError naming a bad chunk
    everything = f"{keys.prefix}/**"
    joint = keys.joint_all()
    regions = keys.region_all()
    states = keys.uav_state("*")
    rules: list[dict[str, Any]] = [
        _rule("fusion-in", ACL_MESSAGES, "ingress", [everything]),
        _rule("fusion-out", ACL_MESSAGES, "egress", [everything]),
    ]
    subjects: list[dict[str, Any]] = [{"id": FUSION_IDENTITY, subject_field: [FUSION_IDENTITY]}]
    policies: list[dict[str, Any]] = [{"id": "fusion", "rules": ["fusion-in", "fusion-out"],
                                       "subjects": [FUSION_IDENTITY]}]
    # what every UAV and operator may receive: joint data, the UAVs' state, replies from the joint queryable
    rules += [
        _rule("fleet-receive", ["put", "reply"], "egress", [joint, regions, states]),
        _rule("fleet-see-queryables", ["declare_queryable", "declare_subscriber"], "egress", [everything]),
        _rule("fleet-subscribe", ["declare_subscriber", "query"], "ingress", [joint, regions, states]),
    ]
    # the fusion shards' liveliness tokens: an agent routes its tiles to their shards (shared.sharding)
    shards = f"{keys.prefix}/fusion/shards/**"
    rules += [
        _rule("fleet-shards-receive", ["liveliness_token"], "egress", [shards]),
        _rule("fleet-shards-watch", ["declare_liveliness_subscriber", "liveliness_query"], "ingress", [shards]),
    ]
    fleet_rules = ["fleet-receive", "fleet-see-queryables", "fleet-subscribe", "fleet-shards-receive",
                   "fleet-shards-watch"]
    for uav in identities.uavs:
        own = [f"{keys.prefix}/uav/{uav}/**"]
        rules += [
            _rule(f"{uav}-put", ["put", "delete"], "ingress", own),
            _rule(f"{uav}-alive", ["liveliness_token"], "ingress", [keys.uav_alive(uav)]),
        ]
        subjects.append({"id": f"uav:{uav}", subject_field: [uav]})
        policies.append({"id": f"uav:{uav}", "rules": [f"{uav}-put", f"{uav}-alive", *fleet_rules],
                         "subjects": [f"uav:{uav}"]})
    if identities.operators:
        rules += [
            _rule("operator-receive", ["put", "reply", "liveliness_token"], "egress", [everything]),
            _rule("operator-subscribe", ["declare_subscriber", "query", "declare_liveliness_subscriber",
                                         "liveliness_query"], "ingress", [everything]),
        ]
        for name in identities.operators:
            subjects.append({"id": f"operator:{name}", subject_field: [name]})
        policies.append({"id": "operators", "rules": ["operator-receive", "operator-subscribe",
                                                      "fleet-see-queryables"],
                         "subjects": [f"operator:{n}" for n in identities.operators]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}
