//! What every DDS entity of the node shares: the QoS profiles of its topics, topics and
//! services by their names in the node's namespace, a node's own (`~/…`) services, and
//! answering a server's waiting requests.

use ros2_client::{
    MessageTypeName, Name, Node, Publisher, QosProfile, Server, ServiceMapping, ServiceTypeName, Subscription,
};

use super::error::{ros_err, NodeError};
use crate::msgs::Message;
use crate::record::Qos;
use crate::session::TopicNames;

/// The QoS profiles of the node's topics (inputs: sensor data, so that both reliable and
/// best-effort publishers connect; reliable writers never wait on a slow reader).
pub fn qos(kind: Qos) -> QosProfile {
    use ros2_client::qos::{Durability, History, Reliability, WhenFull};
    let base = QosProfile::subscription_default();
    match kind {
        Qos::SensorData => base.history(History::KeepLast { depth: 5 }),
        Qos::Reliable => base
            .reliability(Reliability::Reliable { when_full: WhenFull::Fail })
            .history(History::KeepLast { depth: 10 }),
        Qos::Latched => base
            .reliability(Reliability::Reliable { when_full: WhenFull::Fail })
            .durability(Durability::TransientLocal)
            .history(History::KeepLast { depth: 1 }),
    }
}

/// A service under the node's own name (`~/service`), with rmw's services profile
/// (reliable, volatile, the last 10).
pub(super) fn own_server<Req, Resp>(
    node: &mut Node,
    service: &str,
    package: &str,
    ty: &str,
) -> Result<Server<Req, Resp>, NodeError>
where
    Req: ros2_client::Message + Clone + 'static,
    Resp: ros2_client::Message + 'static,
{
    let full = format!("{}/{service}", node.fully_qualified_name());
    let name = Name::parse(&full).map_err(|e| NodeError::Ros(format!("service {full}: {e:?}")))?;
    let q = qos(Qos::Reliable);
    node.create_server(ServiceMapping::Enhanced, &name, &ServiceTypeName::new(package, ty), q.clone(), q)
        .map_err(ros_err(&full))
}

/// Answers every waiting request of `server` with `handle`.
pub(super) fn answer<Req: ros2_client::Message + Clone + 'static, Resp: ros2_client::Message + 'static>(
    server: &Server<Req, Resp>,
    mut handle: impl FnMut(Req) -> Resp,
) {
    while let Ok(Some((id, request))) = server.receive_request() {
        if let Err(e) = server.send_response(id, handle(request)) {
            tracing::warn!("service reply not sent: {e:?}");
        }
    }
}

/// The DDS type name of a message (`package/msg/Type` as `package::msg::dds_::Type_`).
pub(super) fn type_name<T: Message>() -> MessageTypeName {
    let mut parts = T::NAME.split('/');
    let (package, name) = (parts.next().unwrap_or_default(), parts.next_back().unwrap_or_default());
    MessageTypeName::new(package, name)
}

/// Topics and services named relative to the node's namespace, remaps applied.
pub(super) struct Topics<'a> {
    pub names: &'a TopicNames,
}

impl Topics<'_> {
    /// The fully qualified name of a relative topic, remaps applied.
    pub fn resolve(&self, topic: &str) -> String {
        self.names.resolve(topic)
    }

    pub fn publisher<T: Message + ros2_client::Message>(
        &self,
        node: &mut Node,
        topic: &str,
        kind: Qos,
    ) -> Result<(String, Publisher<T>), NodeError> {
        let full = self.resolve(topic);
        let name = Name::parse(&full).map_err(|e| NodeError::Ros(format!("topic {full}: {e:?}")))?;
        let t = node.create_topic(&name, type_name::<T>(), &qos(kind)).map_err(ros_err(&full))?;
        let publisher = node.create_publisher(&t, Some(qos(kind))).map_err(ros_err(&full))?;
        Ok((full, publisher))
    }

    pub fn subscription<T: Message + ros2_client::Message + 'static>(
        &self,
        node: &mut Node,
        topic: &str,
    ) -> Result<(String, Subscription<T>), NodeError> {
        let full = self.resolve(topic);
        let name = Name::parse(&full).map_err(|e| NodeError::Ros(format!("topic {full}: {e:?}")))?;
        let t = node.create_topic(&name, type_name::<T>(), &qos(Qos::SensorData)).map_err(ros_err(&full))?;
        // Sensor-data QoS, but a deep queue: 1 kHz trackers send several poses per tick, and
        // every one is checked and recorded.
        let deep = qos(Qos::SensorData).history(ros2_client::qos::History::KeepLast { depth: 64 });
        let subscription = node.create_subscription(&t, Some(deep)).map_err(ros_err(&full))?;
        Ok((full, subscription))
    }

    pub fn server<Req: ros2_client::Message + Clone + 'static, Resp: ros2_client::Message + 'static>(
        &self,
        node: &mut Node,
        service: &str,
        package: &str,
        ty: &str,
    ) -> Result<Server<Req, Resp>, NodeError> {
        let full = self.resolve(service);
        let name = Name::parse(&full).map_err(|e| NodeError::Ros(format!("service {full}: {e:?}")))?;
        let q = qos(Qos::Reliable);
        node.create_server(ServiceMapping::Enhanced, &name, &ServiceTypeName::new(package, ty), q.clone(), q)
            .map_err(ros_err(&full))
    }
}
