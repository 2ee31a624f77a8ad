//! A managed node's ROS 2 face, named and typed as rclcpp's `LifecycleNode` has it:
//! `~/change_state`, `~/get_state`, `~/get_available_states`,
//! `~/get_available_transitions`, `~/get_transition_graph` and the `~/transition_event`
//! topic, answered from the [`Lifecycle`] state machine.

use ros2_client::{Name, Node, Publisher, Server};

use super::error::{ros_err, NodeError};
use super::lifecycle::{Lifecycle, Outcome, Work};
use super::wire::{answer, own_server, qos};
use crate::msgs::{
    ChangeStateRequest, ChangeStateResponse, GetAvailableStatesResponse, GetAvailableTransitionsResponse,
    GetStateResponse, Message, TransitionEvent, TriggerRequest,
};
use crate::record::Qos;

/// The state machine with its services and its event topic.
pub(super) struct Managed {
    machine: Lifecycle,
    change_state: Server<ChangeStateRequest, ChangeStateResponse>,
    get_state: Server<TriggerRequest, GetStateResponse>,
    available_states: Server<TriggerRequest, GetAvailableStatesResponse>,
    available_transitions: Server<TriggerRequest, GetAvailableTransitionsResponse>,
    transition_graph: Server<TriggerRequest, GetAvailableTransitionsResponse>,
    events: Publisher<TransitionEvent>,
}

impl Managed {
    /// An unconfigured node's lifecycle entities.
    pub(super) fn create(node: &mut Node) -> Result<Self, NodeError> {
        let full = format!("{}/transition_event", node.fully_qualified_name());
        let name = Name::parse(&full).map_err(|e| NodeError::Ros(format!("topic {full}: {e:?}")))?;
        let (package, ty) = TransitionEvent::NAME.split_once("/msg/").unwrap_or_default();
        let qos = qos(Qos::Reliable);
        let topic =
            node.create_topic(&name, ros2_client::MessageTypeName::new(package, ty), &qos).map_err(ros_err(&full))?;
        Ok(Self {
            machine: Lifecycle::default(),
            change_state: own_server(node, "change_state", "lifecycle_msgs", "ChangeState")?,
            get_state: own_server(node, "get_state", "lifecycle_msgs", "GetState")?,
            available_states: own_server(node, "get_available_states", "lifecycle_msgs", "GetAvailableStates")?,
            available_transitions: own_server(
                node,
                "get_available_transitions",
                "lifecycle_msgs",
                "GetAvailableTransitions",
            )?,
            transition_graph: own_server(node, "get_transition_graph", "lifecycle_msgs", "GetAvailableTransitions")?,
            events: node.create_publisher(&topic, Some(qos)).map_err(ros_err(&full))?,
        })
    }

    pub(super) fn is_active(&self) -> bool {
        self.machine.is_active()
    }

    /// Answers every waiting request; a `change_state` runs its transition through `work`
    /// and publishes each state change on `~/transition_event`.
    pub(super) fn serve(&mut self, mut work: impl FnMut(Work) -> Outcome) {
        let Self { machine, events, .. } = self;
        answer(&self.change_state, |request| {
            let publish = |event: TransitionEvent| {
                if let Err(e) = events.publish(event) {
                    tracing::warn!("transition_event not sent: {e:?}");
                }
            };
            let changed = machine.change(request.transition.id, &request.transition.label, &mut work, publish);
            let success = changed.unwrap_or_else(|why| {
                tracing::error!("{why}");
                false
            });
            tracing::info!("lifecycle: {} ({})", machine.state().label, if success { "done" } else { "refused" });
            ChangeStateResponse { success }
        });
        answer(&self.get_state, |_| GetStateResponse { current_state: machine.state() });
        answer(&self.available_states, |_| GetAvailableStatesResponse { available_states: Lifecycle::states() });
        answer(&self.available_transitions, |_| GetAvailableTransitionsResponse {
            available_transitions: machine.available(),
        });
        answer(&self.transition_graph, |_| GetAvailableTransitionsResponse {
            available_transitions: Lifecycle::graph(),
        });
    }
}
