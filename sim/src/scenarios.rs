//! Built-in buildings modelled on the paper's dataset (seq01–seq06) and one for two robots.

use crate::plan::PlanError;
use crate::plan::{Door, FloorPlan, MarkerStyle, Space, SpaceKind};
use crate::render::RenderOptions;
use crate::walk::{walk, Motion, Route, Tour, Visit, Walk, WalkError};
use serde::{Deserialize, Serialize};

fn space(name: &str, kind: SpaceKind, min: [f64; 2], max: [f64; 2]) -> Space {
    Space {
        name: name.into(),
        kind,
        min,
        max,
        looks_like: None,
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
        misprints: Vec::new(),
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
                    1.2,
                ),
                door(
                    "East-north",
                    "North corridor",
                    "East corridor",
                    [12.0, 11.0],
                    1.2,
                ),
                door(
                    "North-west",
                    "West corridor",
                    "North corridor",
                    [2.0, 11.0],
                    1.2,
                ),
                door(
                    "West-south",
                    "South corridor",
                    "West corridor",
                    [1.0, 2.0],
                    1.2,
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

fn visit(space: &str, tour: Tour) -> Visit {
    Visit {
        space: space.into(),
        tour,
    }
}

fn route(robot: &str, start: [f64; 2], visits: Vec<Visit>) -> Route {
    Route {
        robot: robot.into(),
        start: Some(start),
        visits,
    }
}

use Tour::{Loop, Points, Through};

/// The robots' routes of a built-in scenario: every space toured, doors crossed both ways, and
/// a return to the start that closes a loop.
pub fn routes(name: &str) -> Option<Vec<Route>> {
    let one = |start: [f64; 2], visits: Vec<Visit>| vec![route("robot-1", start, visits)];
    Some(match name {
        "seq01" => one(
            [1.5, 2.0],
            vec![
                visit("Lab A", Loop),
                visit("Lab B", Loop),
                visit("Lab A", Points(vec![[2.0, 2.0]])),
            ],
        ),
        "seq02" => one(
            [1.0, 1.0],
            vec![
                visit("Corridor 1", Through),
                visit("Office", Loop),
                visit("Corridor 1", Through),
                visit("Corridor 2", Loop),
                visit("Corridor 1", Points(vec![[1.5, 1.0]])),
            ],
        ),
        "seq03" => {
            let mut visits = vec![];
            for i in 1..=5 {
                visits.push(visit("Corridor", Through));
                visits.push(visit(&format!("Room {i}"), Loop));
            }
            visits.push(visit("Corridor", Points(vec![[10.0, 1.0], [1.5, 1.0]])));
            one([1.0, 1.0], visits)
        }
        "seq04" => one(
            [1.0, 1.0],
            vec![
                visit("Corridor A", Through),
                visit("Landing", Loop),
                visit("Corridor B", Loop),
                visit("Landing", Through),
                visit("Corridor A", Points(vec![[1.5, 1.0]])),
            ],
        ),
        "seq05" => one(
            [3.0, 1.0],
            vec![
                visit("South corridor", Through),
                visit("East corridor", Loop),
                visit("North corridor", Through),
                visit("West corridor", Through),
                visit("South corridor", Through),
                visit("Hall", Loop),
                visit("South corridor", Points(vec![[3.0, 1.0]])),
            ],
        ),
        "seq06" => one(
            [2.0, 2.5],
            vec![
                visit("Lab", Loop),
                visit("Corridor", Loop),
                visit("Lab", Points(vec![[2.0, 2.5]])),
            ],
        ),
        // Each robot enters the hall by its own door and keeps to its half: both pass near
        // enough to the markers in the middle of the south and north walls to map them, only
        // one to the west wall's, only the other to the east wall's, so the hall is a room only
        // in their joined map. Both walk the middle of the corridor, whose markers tell where
        // their maps meet.
        "two_robots" => vec![
            route(
                "robot-1",
                [1.0, 1.0],
                vec![
                    visit("Corridor", Through),
                    visit(
                        "Hall",
                        Points(vec![
                            [4.0, 4.5],
                            [3.2, 6.0],
                            [4.0, 7.5],
                            [7.0, 8.0],
                            [7.4, 8.7],
                            [7.0, 3.5],
                        ]),
                    ),
                    visit("Corridor", Points(vec![[11.0, 1.0], [1.0, 1.0]])),
                ],
            ),
            route(
                "robot-2",
                [15.0, 1.0],
                vec![
                    visit("Corridor", Through),
                    visit(
                        "Hall",
                        Points(vec![
                            [12.0, 4.5],
                            [12.8, 6.0],
                            [12.0, 7.5],
                            [9.0, 8.0],
                            [8.6, 8.7],
                            [9.0, 3.5],
                        ]),
                    ),
                    // Back along the corridor past the middle, where robot-1 mapped too.
                    visit("Corridor", Points(vec![[5.5, 1.0], [15.0, 1.0]])),
                ],
            ),
        ],
        _ => return None,
    })
}

/// Everything needed to simulate a run: the building, the robots' routes, how they move and
/// how the camera renders. Built in by name, or read from a JSON file of this shape (`motion`
/// and `render` optional).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    pub plan: FloorPlan,
    pub routes: Vec<Route>,
    #[serde(default)]
    pub motion: Motion,
    #[serde(default)]
    pub render: RenderOptions,
}

#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    #[error("{0:?} is neither a built-in scenario ({list}) nor a readable file: {1}", list = NAMES.join(", "))]
    NotFound(String, std::io::Error),
    #[error("{path}: not a scenario: {message}")]
    Json { path: String, message: String },
    #[error(transparent)]
    Plan(#[from] PlanError),
    #[error(transparent)]
    Walk(#[from] WalkError),
    #[error("two routes are for robot {0:?}")]
    DuplicateRobot(String),
}

impl Scenario {
    /// The building its plan describes, and a renderer of it whose noise and textures come
    /// from `seed` (the same seed, the same frames).
    pub fn build(&self, seed: u64) -> Result<(crate::Building, crate::Renderer), PlanError> {
        let building = crate::Building::from_plan(&self.plan)?;
        let renderer = crate::Renderer::new(&self.plan, &building, self.render.clone(), seed);
        Ok((building, renderer))
    }

    /// A built-in scenario by name.
    pub fn builtin(name: &str) -> Option<Self> {
        Some(Self {
            plan: scenario(name)?,
            routes: routes(name)?,
            motion: Motion::default(),
            render: RenderOptions::default(),
        })
    }

    /// A built-in name, or the path of a scenario JSON file.
    pub fn load(name_or_path: &str) -> Result<Self, ScenarioError> {
        let scenario = match Self::builtin(name_or_path) {
            Some(s) => s,
            None => {
                let text = std::fs::read_to_string(name_or_path)
                    .map_err(|e| ScenarioError::NotFound(name_or_path.to_owned(), e))?;
                serde_json::from_str(&text).map_err(|e| ScenarioError::Json {
                    path: name_or_path.to_owned(),
                    message: e.to_string(),
                })?
            }
        };
        scenario.check()?;
        Ok(scenario)
    }

    /// Validates the plan and plans every route.
    pub fn check(&self) -> Result<(), ScenarioError> {
        self.plan.validate()?;
        for (i, r) in self.routes.iter().enumerate() {
            if self.routes[..i].iter().any(|o| o.robot == r.robot) {
                return Err(ScenarioError::DuplicateRobot(r.robot.clone()));
            }
            walk(&self.plan, r, &self.motion)?;
        }
        Ok(())
    }

    /// Every robot's walk.
    pub fn walks(&self) -> Result<Vec<Walk>, WalkError> {
        self.routes
            .iter()
            .map(|r| walk(&self.plan, r, &self.motion))
            .collect()
    }
}
