//! Built-in buildings modelled on the paper's dataset (seq01–seq06) and one for two robots.

use crate::plan::{Door, FloorPlan, MarkerStyle, Space, SpaceKind};

fn space(name: &str, kind: SpaceKind, min: [f64; 2], max: [f64; 2]) -> Space {
    Space {
        name: name.into(),
        kind,
        min,
        max,
    }
}

fn door(name: &str, a: &str, b: &str, at: [f64; 2], width: f64) -> Door {
    Door {
        name: name.into(),
        between: [a.into(), b.into()],
        at,
        width,
        height: 2.0,
    }
}

fn plan(name: &str, spaces: Vec<Space>, doors: Vec<Door>) -> FloorPlan {
    FloorPlan {
        name: name.into(),
        wall_height: 2.6,
        markers: MarkerStyle::default(),
        spaces,
        doors,
    }
}

use SpaceKind::{Corridor, Room};

/// Names of the built-in scenarios.
pub const NAMES: [&str; 7] = [
    "seq01",
    "seq02",
    "seq03",
    "seq04",
    "seq05",
    "seq06",
    "two_robots",
];

/// A built-in scenario's floor plan by name.
pub fn scenario(name: &str) -> Option<FloorPlan> {
    Some(match name {
        // Two rooms joined by a door.
        "seq01" => plan(
            name,
            vec![
                space("Lab A", Room, [0.0, 0.0], [5.0, 4.0]),
                space("Lab B", Room, [5.0, 0.0], [9.0, 4.0]),
            ],
            vec![door("Door A-B", "Lab A", "Lab B", [5.0, 2.0], 0.9)],
        ),
        // A corridor joined to a room and to another corridor.
        "seq02" => plan(
            name,
            vec![
                space("Corridor 1", Corridor, [0.0, 0.0], [10.0, 2.0]),
                space("Office", Room, [3.0, 2.0], [7.0, 6.0]),
                space("Corridor 2", Corridor, [10.0, 0.0], [12.0, 10.0]),
            ],
            vec![
                door("Office door", "Corridor 1", "Office", [5.0, 2.0], 0.9),
                door(
                    "Corridor junction",
                    "Corridor 1",
                    "Corridor 2",
                    [10.0, 1.0],
                    1.8,
                ),
            ],
        ),
        // Five rooms on a corridor.
        "seq03" => {
            let mut spaces = vec![space("Corridor", Corridor, [0.0, 0.0], [20.0, 2.0])];
            let mut doors = Vec::new();
            for (i, x0) in [0.0, 4.0, 8.0, 12.0, 16.0].into_iter().enumerate() {
                let name = format!("Room {}", i + 1);
                spaces.push(space(&name, Room, [x0, 2.0], [x0 + 4.0, 6.0]));
                doors.push(door(
                    &format!("{name} door"),
                    "Corridor",
                    &name,
                    [x0 + 2.0, 2.0],
                    0.9,
                ));
            }
            plan(name, spaces, doors)
        }
        // Two corridors joined by a landing.
        "seq04" => plan(
            name,
            vec![
                space("Corridor A", Corridor, [0.0, 0.0], [10.0, 2.0]),
                space("Landing", Room, [10.0, -1.0], [14.0, 3.0]),
                space("Corridor B", Corridor, [14.0, 0.0], [24.0, 2.0]),
            ],
            vec![
                door("Landing west", "Corridor A", "Landing", [10.0, 1.0], 1.5),
                door("Landing east", "Landing", "Corridor B", [14.0, 1.0], 1.5),
            ],
        ),
        // Four corridors and a room forming a loop.
        "seq05" => plan(
            name,
            vec![
                space("South corridor", Corridor, [0.0, 0.0], [12.0, 2.0]),
                space("East corridor", Corridor, [12.0, 0.0], [14.0, 12.0]),
                space("North corridor", Corridor, [2.0, 10.0], [12.0, 12.0]),
                space("West corridor", Corridor, [0.0, 2.0], [2.0, 12.0]),
                space("Hall", Room, [4.0, 2.0], [8.0, 6.0]),
            ],
            vec![
                door(
                    "South-east",
                    "South corridor",
                    "East corridor",
                    [12.0, 1.0],
                    1.8,
                ),
                door(
                    "East-north",
                    "North corridor",
                    "East corridor",
                    [12.0, 11.0],
                    1.8,
                ),
                door(
                    "North-west",
                    "West corridor",
                    "North corridor",
                    [2.0, 11.0],
                    1.8,
                ),
                door(
                    "West-south",
                    "South corridor",
                    "West corridor",
                    [1.0, 2.0],
                    1.8,
                ),
                door("Hall door", "South corridor", "Hall", [6.0, 2.0], 0.9),
            ],
        ),
        // A single room joined to a corridor.
        "seq06" => plan(
            name,
            vec![
                space("Lab", Room, [0.0, 0.0], [4.0, 5.0]),
                space("Corridor", Corridor, [4.0, 0.0], [14.0, 2.0]),
            ],
            vec![door("Lab door", "Lab", "Corridor", [4.0, 1.0], 0.9)],
        ),
        // A large room with two doors onto a corridor: a robot from either door sees only part
        // of the room, so neither alone sees all four of its walls.
        "two_robots" => plan(
            name,
            vec![
                space("Corridor", Corridor, [0.0, 0.0], [16.0, 2.0]),
                space("Hall", Room, [2.0, 2.0], [14.0, 10.0]),
            ],
            vec![
                door("Hall west door", "Corridor", "Hall", [4.0, 2.0], 0.9),
                door("Hall east door", "Corridor", "Hall", [12.0, 2.0], 0.9),
            ],
        ),
        _ => return None,
    })
}
