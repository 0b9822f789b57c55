//! zenoh's access control for a site whose robots hold certificates: each robot may publish
//! frames and declare its liveliness only under its own id, the common name of its certificate
//! ([`crate::certificates`]); anything else a peer sends is refused by zenoh before it reaches
//! ingest. The server's own declarations (its subscriptions, its liveliness) go out to every
//! robot, and every robot may watch the server's liveliness.

use serde_json::{json, Value};
use vsgraphs_proto::keys;

/// Messages a robot may send under its own keys, and the server to robots.
const MESSAGES: [&str; 9] = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
];

/// The `access_control` section of the server's zenoh configuration for `robots`.
pub fn rules(robots: &[String]) -> anyhow::Result<Value> {
    let mut rules = vec![json!({
        "id": "server to robots",
        "permission": "allow",
        "flows": ["egress"],
        "messages": MESSAGES,
        "key_exprs": ["vsgraphs/**"],
    })];
    rules.push(json!({
        "id": "robots watch the server",
        "permission": "allow",
        "flows": ["ingress"],
        "messages": ["declare_liveliness_subscriber", "liveliness_query"],
        "key_exprs": [keys::SERVER_ALIVE],
    }));
    let mut subjects = Vec::new();
    let mut policies = Vec::new();
    for (i, id) in robots.iter().enumerate() {
        // An id is a literal key chunk: no wildcards, no separators.
        keys::validate_robot_id(id).map_err(|e| anyhow::anyhow!("robot id {id:?}: {e}"))?;
        let subject = format!("robot {i}");
        let rule = format!("robot {i} under its id");
        rules.push(json!({
            "id": rule,
            "permission": "allow",
            "flows": ["ingress"],
            "messages": MESSAGES,
            "key_exprs": [keys::robot(id)],
        }));
        subjects.push(json!({ "id": subject, "cert_common_names": [id] }));
        policies.push(json!({
            "rules": [rule, "server to robots", "robots watch the server"],
            "subjects": [subject],
        }));
    }
    Ok(json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }))
}
