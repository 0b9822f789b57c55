//! zenoh's access control for a site whose robots hold certificates: each robot may publish
//! frames and declare its liveliness only under its own id, the common name of its certificate
//! ([`crate::certificates`]); anything else a peer sends is refused by zenoh before it reaches
//! ingest. The server's own declarations (its subscriptions, its liveliness) go out to every
//! robot, and every robot may watch the server's liveliness.
//!
//! A ROS 2 robot of `[[ros.robots]]` (its router or bridge holding the certificate named as the
//! robot) may also put messages on its three topics' keys and declare the liveliness tokens of
//! their publishers, and the server's subscriptions to those keys go out to it.

use crate::config::RosRobotConfig;
use crate::ingest::ros;
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

/// The `access_control` section of the server's zenoh configuration for `robots`, of which
/// `ros_robots` are ROS 2 robots.
pub fn rules(robots: &[String], ros_robots: &[RosRobotConfig]) -> anyhow::Result<Value> {
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
        let mut allowed = vec![
            json!(rule),
            json!("server to robots"),
            json!("robots watch the server"),
        ];
        if let Some(ros_robot) = ros_robots.iter().find(|r| &r.id == id) {
            let topics = ros::key_expressions(ros_robot);
            let (to_server, to_robot) = (
                format!("{rule}: ROS topics"),
                format!("{rule}: ROS subscriptions"),
            );
            rules.push(json!({
                "id": to_server,
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["put", "liveliness_token"],
                "key_exprs": topics,
            }));
            rules.push(json!({
                "id": to_robot,
                "permission": "allow",
                "flows": ["egress"],
                "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
                "key_exprs": topics,
            }));
            allowed.extend([json!(to_server), json!(to_robot)]);
        }
        policies.push(json!({
            "rules": allowed,
            "subjects": [subject],
        }));
    }
    if let Some(stray) = ros_robots.iter().find(|r| !robots.contains(&r.id)) {
        anyhow::bail!(
            "ROS robot {:?} is not in [ingest] allowed_robots: under the access rules each robot \
             needs a certificate under its id",
            stray.id
        );
    }
    Ok(json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }))
}
