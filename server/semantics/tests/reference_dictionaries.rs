//! Every dictionary of the reference implementation's dataset (`../shared/reference/
//! env_database`, both versions) parses; their known mistakes come out as warnings.

use std::path::PathBuf;
use vsgraphs_semantics::dictionary::{Dictionary, MarkerRole, SpaceKind, Version};

fn reference_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("VSGRAPHS_TEST_DATA")
        .map(|d| PathBuf::from(d).join("../reference/env_database"))
        .unwrap_or_else(|| {
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/reference/env_database")
        });
    if dir.is_dir() {
        Some(dir)
    } else {
        eprintln!("SKIPPED: no reference dictionaries at {}", dir.display());
        None
    }
}

fn read(dir: &std::path::Path, name: &str) -> Dictionary {
    Dictionary::read(&dir.join(name)).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn every_reference_dictionary_parses() {
    let Some(dir) = reference_dir() else { return };
    let mut files = 0;
    for version in ["v1", "v2"] {
        for entry in std::fs::read_dir(dir.join(version)).unwrap() {
            let path = entry.unwrap().path();
            let d = Dictionary::read(&path).unwrap_or_else(|e| panic!("{e}"));
            let expected = if version == "v1" {
                Version::V1
            } else {
                Version::V2
            };
            assert_eq!(d.version, expected, "{}", path.display());
            assert!(!d.spaces.is_empty(), "{}", path.display());
            for w in &d.warnings {
                eprintln!("{}: {w}", path.display());
            }
            files += 1;
        }
    }
    assert_eq!(files, 13);
}

#[test]
fn the_known_mistakes_are_reported() {
    let Some(dir) = reference_dir() else { return };
    // v2 seq03 (and seq02) name two doors by marker 9.
    for file in ["v2/autosense_seq03.json", "v2/autosense_seq02.json"] {
        let d = read(&dir, file);
        assert_eq!(d.warnings.len(), 1, "{file}: {:?}", d.warnings);
        assert!(d.warnings[0].contains("marker 9 names two doors"), "{file}");
    }
    // v1 seq04 lists markers 5 and 13 as one corridor's wall markers and the other's door
    // markers: they are door markers.
    let d = read(&dir, "v1/ulms_seq04_jfk_e04_cor.json");
    assert_eq!(d.warnings.len(), 2, "{:?}", d.warnings);
    assert!(matches!(d.role(5), MarkerRole::Door { door: Some(_) }));
    assert!(matches!(d.role(13), MarkerRole::Door { door: Some(_) }));
    // The others are clean.
    for file in [
        "v1/ulms_seq01_aerolab.json",
        "v1/ulms_seq03_jfk_e04_ofc.json",
        "v2/autosense_seq06.json",
    ] {
        assert!(read(&dir, file).warnings.is_empty(), "{file}");
    }
}

#[test]
fn the_paper_s_first_sequence_reads_as_its_building() {
    let Some(dir) = reference_dir() else { return };
    let d = read(&dir, "v1/ulms_seq01_aerolab.json");
    let corridor = d.space("AeRoLab Corr.").unwrap();
    let lab = d.space("Welding Lab.").unwrap();
    assert_eq!(d.spaces[corridor].kind, SpaceKind::Corridor);
    assert_eq!(d.spaces[lab].kind, SpaceKind::Room);
    assert_eq!(d.spaces[lab].wall_groups, [vec![0, 2, 4, 5]]);
    assert_eq!(d.role(9), MarkerRole::Wall { space: corridor });
    let door = d
        .doors
        .iter()
        .position(|x| x.name == "AeRoLab Door")
        .unwrap();
    assert_eq!(d.role(7), MarkerRole::Door { door: Some(door) });
    assert_eq!(d.spaces_of_door(7), [corridor]);
}
