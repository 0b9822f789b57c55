//! Semantic dictionaries as a user could write them wrong: arbitrary text, and valid
//! dictionaries of both versions changed value by value (ids out of range, groups of any size,
//! one id in two places, wrong types, missing and extra keys). Each is read or refused with a
//! problem; none panics; one that is read is consistent: every role points at an entry that
//! exists, and every space is found by its name.

use proptest::prelude::*;
use serde_json::{json, Value};
use std::path::PathBuf;
use vsgraphs_semantics::dictionary::{Dictionary, MarkerRole};

/// Dictionaries to start from: two of our own (one per version) and, when the shared data is
/// beside the repository, the reference implementation's.
fn valid() -> &'static [Value] {
    static VALID: std::sync::OnceLock<Vec<Value>> = std::sync::OnceLock::new();
    VALID.get_or_init(|| {
        let mut all = vec![
            json!({
                "rooms": [
                    {"name": "Hall", "markers": [[1, 2], [3, 4]], "doorMarkers": [10, 11]},
                    {"name": "Lab", "markers": [[5, 6, 7, 8]], "doorMarkers": [10]},
                    {"name": "Store", "markers": [[20, 21, 22, 23]], "doorMarkers": [11]}
                ],
                "doors": [{"name": "Lab door", "marker": 10}, {"name": "Store door", "marker": 11}]
            }),
            json!({
                "rooms": [
                    {"name": "Office", "isCorridor": false, "metaMarker": 5, "doorMarkers": [30]},
                    {"name": "Corridor", "isCorridor": true, "metaMarker": 6, "doorMarkers": [30, 31]}
                ],
                "doors": [{"name": "Office door", "marker": 30}]
            }),
        ];
        let shared = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../../../shared/reference/env_database");
        for version in ["v1", "v2"] {
            let Ok(entries) = std::fs::read_dir(shared.join(version)) else {
                continue;
            };
            for entry in entries.flatten() {
                let text = std::fs::read_to_string(entry.path()).unwrap();
                all.push(serde_json::from_str(&text).unwrap());
            }
        }
        for value in &all {
            Dictionary::parse(&value.to_string()).unwrap();
        }
        all
    })
}

/// A value to put somewhere in a dictionary.
fn any_value() -> impl Strategy<Value = Value> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::from),
        (-3i64..40).prop_map(Value::from),
        prop_oneof![
            Just(i64::MIN),
            Just(i64::MAX),
            Just(i64::from(i32::MAX) + 1)
        ]
        .prop_map(Value::from),
        any::<f64>().prop_map(|f| json!(f)),
        "[A-Za-z .]{0,12}".prop_map(Value::from),
    ];
    leaf.prop_recursive(3, 16, 6, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..6).prop_map(Value::from),
            prop::collection::btree_map(
                prop_oneof![
                    Just("name".to_owned()),
                    Just("markers".to_owned()),
                    Just("doorMarkers".to_owned()),
                    Just("metaMarker".to_owned()),
                    Just("isCorridor".to_owned()),
                    Just("marker".to_owned()),
                    "[a-z]{1,6}"
                ],
                inner,
                0..5
            )
            .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    })
}

/// What to do at the node a path of choices leads to.
#[derive(Debug, Clone)]
enum Change {
    Replace(Value),
    /// A number becomes this one (other values stay): ids out of range, or one id in two places.
    Renumber(i64),
    Remove,
    /// In an array: repeat an element; in an object: add a key.
    Grow(Value),
}

fn change() -> impl Strategy<Value = (Vec<usize>, Change)> {
    (
        prop::collection::vec(any::<usize>(), 0..6),
        prop_oneof![
            2 => any_value().prop_map(Change::Replace),
            4 => prop_oneof![
                8 => -2i64..40,
                1 => Just(i64::from(i32::MAX) + 1),
                1 => Just(i64::MIN),
            ]
            .prop_map(Change::Renumber),
            1 => Just(Change::Remove),
            2 => any_value().prop_map(Change::Grow),
        ],
    )
}

/// Follows `path` (each step an index among the node's children, modulo their number) as far
/// as it goes and applies `change` there.
fn apply(node: &mut Value, path: &[usize], change: Change) {
    let children = match node {
        Value::Array(items) => items.len(),
        Value::Object(map) => map.len(),
        _ => 0,
    };
    if let Some((&step, rest)) = path.split_first().filter(|_| children > 0) {
        let i = step % children;
        if rest.is_empty() {
            match (node, change) {
                (Value::Array(items), Change::Renumber(n)) if items[i].is_number() => {
                    items[i] = n.into()
                }
                (Value::Object(map), Change::Renumber(n)) => {
                    if let Some(v) = map.values_mut().nth(i).filter(|v| v.is_number()) {
                        *v = n.into();
                    }
                }
                (_, Change::Renumber(_)) => {}
                (Value::Array(items), Change::Remove) => {
                    items.remove(i);
                }
                (Value::Array(items), Change::Grow(_)) => {
                    let copy = items[i].clone();
                    items.insert(i, copy);
                }
                (Value::Array(items), Change::Replace(v)) => items[i] = v,
                (Value::Object(map), Change::Remove) => {
                    let key = map.keys().nth(i).unwrap().clone();
                    map.remove(&key);
                }
                (Value::Object(map), Change::Grow(v)) => {
                    let key = map.keys().nth(i).unwrap().clone();
                    map.insert(format!("{key}x"), v);
                }
                (Value::Object(map), Change::Replace(v)) => {
                    *map.values_mut().nth(i).unwrap() = v;
                }
                _ => unreachable!("only arrays and objects have children"),
            }
            return;
        }
        let child = match node {
            Value::Array(items) => &mut items[i],
            Value::Object(map) => map.values_mut().nth(i).unwrap(),
            _ => unreachable!("only arrays and objects have children"),
        };
        apply(child, rest, change);
    } else {
        match change {
            Change::Replace(v) => *node = v,
            Change::Renumber(n) if node.is_number() => *node = n.into(),
            _ => {}
        }
    }
}

/// A dictionary that was read holds together.
fn check_consistent(d: &Dictionary) -> Result<(), TestCaseError> {
    for (i, space) in d.spaces.iter().enumerate() {
        prop_assert_eq!(d.space(&space.name), Some(i));
        let markers = space.wall_groups.iter().flatten().chain(&space.meta_marker);
        for &m in markers.chain(&space.door_markers) {
            match d.role(m) {
                MarkerRole::Wall { space } | MarkerRole::Meta { space } => {
                    prop_assert!(space < d.spaces.len())
                }
                MarkerRole::Door { door } => {
                    prop_assert!(door.is_none_or(|j| j < d.doors.len()));
                    prop_assert!(d.spaces_of_door(m).iter().all(|&s| s < d.spaces.len()));
                }
                MarkerRole::Unlisted => {
                    prop_assert!(false, "marker {} of {:?} unlisted", m, space.name)
                }
            }
        }
    }
    Ok(())
}

fn cases() -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(2000)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: cases(), ..ProptestConfig::default() })]

    #[test]
    fn changed_dictionaries_are_read_consistent_or_refused(
        base in any::<prop::sample::Index>(),
        changes in prop::collection::vec(change(), 1..4),
    ) {
        let all = valid();
        let mut value = base.get(all).clone();
        for (path, change) in changes {
            apply(&mut value, &path, change);
        }
        match Dictionary::parse(&value.to_string()) {
            Ok(d) => check_consistent(&d)?,
            Err(problem) => prop_assert!(!problem.to_string().is_empty()),
        }
    }

    #[test]
    fn arbitrary_text_is_refused_or_read(text in ".{0,200}", base in any::<prop::sample::Index>(), cut in any::<prop::sample::Index>()) {
        let _ = Dictionary::parse(&text);
        // A valid dictionary cut anywhere and followed by the text.
        let valid = base.get(valid()).to_string();
        let at = cut.index(valid.len() + 1);
        if valid.is_char_boundary(at) {
            if let Ok(d) = Dictionary::parse(&format!("{}{text}", &valid[..at])) {
                check_consistent(&d)?;
            }
        }
    }
}
