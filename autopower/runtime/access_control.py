"""The team's access policy (`protocol.access`) as Zenoh's ``access_control`` section.

Default deny, enforced on ingress by every node that accepts connections: a peer's messages are
matched by the common name of the certificate its link authenticated with. Each member may
declare subscribers, liveliness subscribers and liveliness queries anywhere in the team's key
space (reading is not what an attacker inside the team gains from), but may put only on the keys
`TeamAccess.puts` gives it and hold only its own liveliness token; only the operator identity
may query the base station's operator key and only the base station may answer it. Strangers
have no subject at all, and everything not allowed is denied.
"""

from __future__ import annotations

from autopower.protocol.access import OPERATOR, TeamAccess


def zenoh_access_control(access: TeamAccess) -> dict:
    """Zenoh's ``access_control`` section for one node of the team (the same on every node)."""
    keys = access.keys
    everything = [f"{keys.prefix}/**"]
    rules: list[dict] = [
        # what this node sends to an authenticated peer is not restricted (the peer's own ACL
        # judges it); without this rule default deny would also apply to egress
        {"id": "send", "permission": "allow", "flows": ["egress"],
         "messages": ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                      "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"],
         "key_exprs": everything},
        {"id": "read", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
         "key_exprs": everything},
        {"id": "operator-query", "permission": "allow", "flows": ["ingress"],
         "messages": ["query"], "key_exprs": [keys.operator]},
        {"id": "operator-serve", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_queryable", "reply"], "key_exprs": [keys.operator]},
    ]
    subjects: list[dict] = []
    policies: list[dict] = []
    for identity in access.members:
        subject = f"node-{identity}"
        subjects.append({"id": subject, "cert_common_names": [identity]})
        rules.append({"id": f"put-{identity}", "permission": "allow", "flows": ["ingress"],
                      "messages": ["put"], "key_exprs": list(access.puts(identity))})
        rules.append({"id": f"alive-{identity}", "permission": "allow", "flows": ["ingress"],
                      "messages": ["liveliness_token"], "key_exprs": list(access.liveliness(identity))})
        own = ["send", "read", f"put-{identity}", f"alive-{identity}"]
        if identity == access.basestation:
            own.append("operator-serve")
        policies.append({"id": f"policy-{identity}", "rules": own, "subjects": [subject]})
    subjects.append({"id": "operator", "cert_common_names": [OPERATOR]})
    policies.append({"id": "policy-operator", "rules": ["send", "operator-query"], "subjects": ["operator"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}
