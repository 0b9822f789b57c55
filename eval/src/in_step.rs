//! Robots that take turns a frame at a time, for `vsgraphs-eval scenario --all-robots
//! --in-step`: robot `r`'s frame `i` goes into the pipeline after every robot's frame `i − 1`
//! and after robot `r − 1`'s frame `i`. A live server sees robots that stream at once this way
//! (their maps grow side by side, so they meet young), but here the order is the same on every
//! run, and so are the merges (looked for on each robot's worker).

use std::sync::{Condvar, Mutex, MutexGuard};

/// The turn, and the maps each robot started during its turns (by the map service's ids).
pub struct InStep {
    state: Mutex<State>,
    turn_changed: Condvar,
}

struct State {
    /// Whose frame goes in next.
    turn: usize,
    /// Robots whose walk is not over.
    walking: Vec<bool>,
    /// The map service's next id when the current turn began.
    next_map_at_turn: u32,
    started: Vec<Vec<u32>>,
}

impl InStep {
    /// `robots` robots, robot 0 first; `next_map` is the service's next map id now.
    pub fn new(robots: usize, next_map: u32) -> Self {
        Self {
            state: Mutex::new(State {
                turn: 0,
                walking: vec![true; robots],
                next_map_at_turn: next_map,
                started: vec![Vec::new(); robots],
            }),
            turn_changed: Condvar::new(),
        }
    }

    /// Robot `robot`'s frames, each let through on its turn. `next_map` gives the map service's
    /// next id, read at the end of each turn: the maps made meanwhile are the robot's.
    pub fn frames<'a, I: Iterator>(
        &'a self,
        robot: usize,
        frames: I,
        next_map: &'a (dyn Fn() -> u32 + Sync),
    ) -> Turns<'a, I> {
        Turns {
            step: self,
            robot,
            frames,
            next_map,
            on_turn: false,
        }
    }

    /// The maps each robot started, oldest first.
    pub fn started(&self) -> Vec<Vec<u32>> {
        self.lock().started.clone()
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A robot's run that panicked must not stop the others' turns.
        self.state
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    fn wait_for_turn(&self, robot: usize) {
        let mut state = self.lock();
        while state.turn != robot {
            state = self
                .turn_changed
                .wait(state)
                .unwrap_or_else(|poisoned| poisoned.into_inner());
        }
    }

    /// Ends `robot`'s turn: the maps made during it are its; the turn goes to the next robot
    /// still walking.
    fn end_turn(&self, robot: usize, next_map: u32, walking: bool) {
        let mut state = self.lock();
        let made = state.next_map_at_turn..next_map;
        state.started[robot].extend(made);
        state.next_map_at_turn = next_map;
        state.walking[robot] = walking;
        Self::pass(&mut state, robot);
        drop(state);
        self.turn_changed.notify_all();
    }

    /// `robot` walks no more without having taken a turn.
    fn leave(&self, robot: usize) {
        let mut state = self.lock();
        state.walking[robot] = false;
        if state.turn == robot {
            Self::pass(&mut state, robot);
        }
        drop(state);
        self.turn_changed.notify_all();
    }

    /// The turn to the robot after `robot` still walking (itself when it is the last).
    fn pass(state: &mut State, robot: usize) {
        let robots = state.walking.len();
        if let Some(next) = (1..=robots)
            .map(|k| (robot + k) % robots)
            .find(|&r| state.walking[r])
        {
            state.turn = next;
        }
    }
}

/// One robot's frames through [`InStep`]: a frame is taken on the robot's turn, and the turn
/// ends when the next is asked for (the frame was processed) or the walk ends.
pub struct Turns<'a, I> {
    step: &'a InStep,
    robot: usize,
    frames: I,
    next_map: &'a (dyn Fn() -> u32 + Sync),
    on_turn: bool,
}

impl<I: Iterator> Iterator for Turns<'_, I> {
    type Item = I::Item;

    fn next(&mut self) -> Option<I::Item> {
        if self.on_turn {
            self.step.end_turn(self.robot, (self.next_map)(), true);
        }
        self.step.wait_for_turn(self.robot);
        self.on_turn = true;
        let frame = self.frames.next();
        if frame.is_none() {
            self.on_turn = false;
            self.step.end_turn(self.robot, (self.next_map)(), false);
        }
        frame
    }
}

impl<I> Drop for Turns<'_, I> {
    /// A run that stops early (an error) leaves the turns to the others.
    fn drop(&mut self) {
        if self.on_turn {
            self.step.end_turn(self.robot, (self.next_map)(), false);
        } else {
            self.step.leave(self.robot);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn robots_take_turns_a_frame_each_and_a_finished_walk_is_skipped() {
        let step = InStep::new(3, 0);
        let order = Mutex::new(Vec::new());
        let next_map = || 0;
        let lengths = [3, 1, 2];
        std::thread::scope(|scope| {
            for (robot, &length) in lengths.iter().enumerate() {
                let (step, order) = (&step, &order);
                scope.spawn(move || {
                    for frame in step.frames(robot, 0..length, &next_map) {
                        order.lock().unwrap().push((robot, frame));
                    }
                });
            }
        });
        assert_eq!(
            order.into_inner().unwrap(),
            [(0, 0), (1, 0), (2, 0), (0, 1), (2, 1), (0, 2)]
        );
    }

    #[test]
    fn the_maps_made_on_a_robots_turn_are_its() {
        let step = InStep::new(2, 5);
        let next = std::sync::atomic::AtomicU32::new(5);
        let next_map = || next.load(std::sync::atomic::Ordering::SeqCst);
        std::thread::scope(|scope| {
            for robot in 0..2 {
                let (step, next) = (&step, &next);
                let next_map = &next_map;
                scope.spawn(move || {
                    for frame in step.frames(robot, 0..3, next_map) {
                        // Robot 0 starts a map at its first frame, robot 1 at its first and
                        // its last.
                        if frame == 0 || (robot == 1 && frame == 2) {
                            next.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                        }
                    }
                });
            }
        });
        assert_eq!(step.started(), [vec![5], vec![6, 7]]);
    }

    #[test]
    fn a_robot_whose_run_stops_early_leaves_the_turns_to_the_others() {
        let step = InStep::new(2, 0);
        let next_map = || 0;
        let taken = std::thread::scope(|scope| {
            let first = scope.spawn(|| step.frames(0, 0..10, &next_map).take(2).count());
            let second = scope.spawn(|| step.frames(1, 0..10, &next_map).count());
            (first.join().unwrap(), second.join().unwrap())
        });
        assert_eq!(taken, (2, 10));
    }
}
