//! The managed (lifecycle) node's state machine: rcl_lifecycle's default one, which rclcpp's
//! and rclpy's `LifecycleNode` both run, with its states, its transition graph (ids, labels
//! and order as `get_transition_graph` lists them) and its rules: a transition is requested
//! from a primary state by id or label (the label wins, as rclcpp reads it), the node passes
//! through the transition state while its callback runs, and the callback's outcome picks
//! the edge out of it. Each state change is one `TransitionEvent`. No ROS here: the node
//! wires the services and the topic.

use crate::msgs::{LifecycleState, LifecycleTransition, TransitionDescription, TransitionEvent};

/// State ids (lifecycle_msgs/msg/State).
pub mod state {
    pub const UNKNOWN: u8 = 0;
    pub const UNCONFIGURED: u8 = 1;
    pub const INACTIVE: u8 = 2;
    pub const ACTIVE: u8 = 3;
    pub const FINALIZED: u8 = 4;
    pub const CONFIGURING: u8 = 10;
    pub const CLEANINGUP: u8 = 11;
    pub const SHUTTINGDOWN: u8 = 12;
    pub const ACTIVATING: u8 = 13;
    pub const DEACTIVATING: u8 = 14;
    pub const ERRORPROCESSING: u8 = 15;
}

/// The states, in rcl_lifecycle's order (`get_available_states`).
const STATES: [(u8, &str); 11] = [
    (state::UNKNOWN, "unknown"),
    (state::UNCONFIGURED, "unconfigured"),
    (state::INACTIVE, "inactive"),
    (state::ACTIVE, "active"),
    (state::FINALIZED, "finalized"),
    (state::CONFIGURING, "configuring"),
    (state::CLEANINGUP, "cleaningup"),
    (state::SHUTTINGDOWN, "shuttingdown"),
    (state::ACTIVATING, "activating"),
    (state::DEACTIVATING, "deactivating"),
    (state::ERRORPROCESSING, "errorprocessing"),
];

const SUCCESS: &str = "transition_success";
const FAILURE: &str = "transition_failure";
const ERROR: &str = "transition_error";

/// The transition graph, (id, label, start, goal), in rcl_lifecycle's order. Ids below 10
/// are the ones a user may request; the others follow a callback's outcome.
const GRAPH: [(u8, &str, u8, u8); 25] = {
    use state::*;
    [
        (1, "configure", UNCONFIGURED, CONFIGURING),
        (10, SUCCESS, CONFIGURING, INACTIVE),
        (11, FAILURE, CONFIGURING, UNCONFIGURED),
        (12, ERROR, CONFIGURING, ERRORPROCESSING),
        (2, "cleanup", INACTIVE, CLEANINGUP),
        (20, SUCCESS, CLEANINGUP, UNCONFIGURED),
        (21, FAILURE, CLEANINGUP, INACTIVE),
        (22, ERROR, CLEANINGUP, ERRORPROCESSING),
        (3, "activate", INACTIVE, ACTIVATING),
        (30, SUCCESS, ACTIVATING, ACTIVE),
        (31, FAILURE, ACTIVATING, INACTIVE),
        (32, ERROR, ACTIVATING, ERRORPROCESSING),
        (4, "deactivate", ACTIVE, DEACTIVATING),
        (40, SUCCESS, DEACTIVATING, INACTIVE),
        (41, FAILURE, DEACTIVATING, ACTIVE),
        (42, ERROR, DEACTIVATING, ERRORPROCESSING),
        (5, "shutdown", UNCONFIGURED, SHUTTINGDOWN),
        (6, "shutdown", INACTIVE, SHUTTINGDOWN),
        (7, "shutdown", ACTIVE, SHUTTINGDOWN),
        (50, SUCCESS, SHUTTINGDOWN, FINALIZED),
        (51, FAILURE, SHUTTINGDOWN, FINALIZED),
        (52, ERROR, SHUTTINGDOWN, ERRORPROCESSING),
        (60, SUCCESS, ERRORPROCESSING, UNCONFIGURED),
        (61, FAILURE, ERRORPROCESSING, FINALIZED),
        (62, ERROR, ERRORPROCESSING, FINALIZED),
    ]
};

/// The work a transition state asks of the node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Work {
    /// Load the scene, allocate, make the node's entities.
    Configure,
    /// Free what configure made.
    Cleanup,
    /// Start the outputs and the recording.
    Activate,
    /// Stop the outputs; keep the state.
    Deactivate,
    /// Free everything, from whichever state.
    Shutdown,
    /// After a callback's error: free everything, back to unconfigured if that works.
    ErrorProcessing,
}

/// What a callback says (rclcpp's `CallbackReturn`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    Success,
    /// Refused, nothing changed (a bad scene): back to the start state.
    Failure(String),
    /// Broken half way: the error processing cleans up.
    Error(String),
}

/// A managed node's current state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Lifecycle {
    current: u8,
}

impl Default for Lifecycle {
    fn default() -> Self {
        Self { current: state::UNCONFIGURED }
    }
}

fn state_msg(id: u8) -> LifecycleState {
    let label = STATES.iter().find(|(s, _)| *s == id).map_or("unknown", |(_, label)| label);
    LifecycleState { id, label: label.to_owned() }
}

fn description(&(id, label, start, goal): &(u8, &str, u8, u8)) -> TransitionDescription {
    TransitionDescription {
        transition: LifecycleTransition { id, label: label.to_owned() },
        start_state: state_msg(start),
        goal_state: state_msg(goal),
    }
}

impl Lifecycle {
    pub fn state(&self) -> LifecycleState {
        state_msg(self.current)
    }

    pub fn is_active(&self) -> bool {
        self.current == state::ACTIVE
    }

    /// `get_available_states`: every state.
    pub fn states() -> Vec<LifecycleState> {
        STATES.iter().map(|(id, _)| state_msg(*id)).collect()
    }

    /// `get_transition_graph`: every edge.
    pub fn graph() -> Vec<TransitionDescription> {
        GRAPH.iter().map(description).collect()
    }

    /// `get_available_transitions`: the edges leaving the current state.
    pub fn available(&self) -> Vec<TransitionDescription> {
        GRAPH.iter().filter(|edge| edge.2 == self.current).map(description).collect()
    }

    /// `change_state`: the transition asked for by `label` (when given) or `id`, run through
    /// `work`, each state change told to `emit`; true when the callback succeeded. A
    /// transition the current state does not offer changes nothing and says why.
    pub fn change(
        &mut self,
        id: u8,
        label: &str,
        mut work: impl FnMut(Work) -> Outcome,
        mut emit: impl FnMut(TransitionEvent),
    ) -> Result<bool, String> {
        let requested = GRAPH.iter().filter(|edge| edge.2 == self.current && edge.0 < 10);
        let edge = if label.is_empty() {
            requested.clone().find(|edge| edge.0 == id)
        } else {
            requested.clone().find(|edge| edge.1 == label)
        };
        let Some(&(id, _, _, through)) = edge else {
            let asked = if label.is_empty() { id.to_string() } else { format!("'{label}'") };
            return Err(format!("Unable to start transition {asked} from current state {}", self.state().label));
        };
        self.move_to(through, &mut emit);
        let outcome = work(match id {
            1 => Work::Configure,
            2 => Work::Cleanup,
            3 => Work::Activate,
            4 => Work::Deactivate,
            _ => Work::Shutdown,
        });
        let succeeded = outcome == Outcome::Success;
        self.follow(&outcome, &mut emit);
        if self.current == state::ERRORPROCESSING {
            let outcome = work(Work::ErrorProcessing);
            self.follow(&outcome, &mut emit);
        }
        Ok(succeeded)
    }

    /// Out of a transition state by the edge `outcome` names.
    fn follow(&mut self, outcome: &Outcome, emit: &mut impl FnMut(TransitionEvent)) {
        let label = match outcome {
            Outcome::Success => SUCCESS,
            Outcome::Failure(why) => {
                tracing::warn!("{}: {why}", self.state().label);
                FAILURE
            }
            Outcome::Error(why) => {
                tracing::error!("{}: {why}", self.state().label);
                ERROR
            }
        };
        if let Some(&(_, _, _, goal)) = GRAPH.iter().find(|edge| edge.2 == self.current && edge.1 == label) {
            self.move_to(goal, emit);
        }
    }

    /// One state change, told as rcl_lifecycle tells it: the start and goal states, the
    /// transition left empty.
    fn move_to(&mut self, goal: u8, emit: &mut impl FnMut(TransitionEvent)) {
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
        emit(TransitionEvent {
            timestamp: u64::try_from(now.as_nanos()).unwrap_or(u64::MAX),
            transition: LifecycleTransition::default(),
            start_state: self.state(),
            goal_state: state_msg(goal),
        });
        self.current = goal;
    }
}

#[cfg(test)]
mod tests {
    use crate::ros::lifecycle::{state, Lifecycle, Outcome, Work};

    /// (start, goal) of each event of one change.
    fn run(machine: &mut Lifecycle, id: u8, label: &str, outcome: Outcome) -> (Result<bool, String>, Vec<(u8, u8)>) {
        let mut events = Vec::new();
        let result = machine.change(
            id,
            label,
            |work| if work == Work::ErrorProcessing { Outcome::Success } else { outcome.clone() },
            |e| events.push((e.start_state.id, e.goal_state.id)),
        );
        (result, events)
    }

    #[test]
    fn each_outcome_leaves_its_transition_state_by_rcl_lifecycles_edge() {
        use state::*;
        let mut m = Lifecycle::default();
        let (ok, events) = run(&mut m, 1, "", Outcome::Failure("bad scene".into()));
        assert_eq!((ok, events), (Ok(false), vec![(UNCONFIGURED, CONFIGURING), (CONFIGURING, UNCONFIGURED)]));
        let (ok, events) = run(&mut m, 1, "", Outcome::Error("broken".into()));
        let through_error =
            vec![(UNCONFIGURED, CONFIGURING), (CONFIGURING, ERRORPROCESSING), (ERRORPROCESSING, UNCONFIGURED)];
        assert_eq!((ok, events), (Ok(false), through_error));
        assert_eq!(run(&mut m, 0, "configure", Outcome::Success).0, Ok(true));
        assert_eq!(m.state().id, INACTIVE);
        assert_eq!(run(&mut m, 3, "", Outcome::Success).1, vec![(INACTIVE, ACTIVATING), (ACTIVATING, ACTIVE)]);
        assert!(m.is_active());
        // From active: only deactivate (4) and shutdown (7); a label wins over the id.
        let ids: Vec<u8> = m.available().iter().map(|t| t.transition.id).collect();
        assert_eq!(ids, [4, 7]);
        let refused = run(&mut m, 1, "", Outcome::Success).0.unwrap_err();
        assert_eq!(refused, "Unable to start transition 1 from current state active");
        assert!(run(&mut m, 4, "configure", Outcome::Success).0.is_err());
        assert_eq!(m.state().id, ACTIVE, "a refused transition changes nothing");
        assert_eq!(
            run(&mut m, 0, "shutdown", Outcome::Success).1,
            vec![(ACTIVE, SHUTTINGDOWN), (SHUTTINGDOWN, FINALIZED)]
        );
        assert!(m.available().is_empty());
    }
}
