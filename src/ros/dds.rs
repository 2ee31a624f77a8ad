//! The DDS participant: loopback-only unless a user opens it. ros2-client's default
//! context multicasts on every interface and ignores the `ROS_*` variables, so the node
//! builds its own participant from the environment the ROS 2 way.

use std::net::Ipv4Addr;

#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum DdsError {
    #[error("ROS_DOMAIN_ID=`{0}`: expected a domain id 0..=232")]
    DomainId(String),
    #[error("ROS_AUTOMATIC_DISCOVERY_RANGE=`{0}`: expected LOCALHOST, SUBNET, OFF or SYSTEM_DEFAULT")]
    DiscoveryRange(String),
    #[error("DDS participant: {0}")]
    Participant(String),
}

/// Where discovery may reach.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Discovery {
    /// 127.0.0.1 only: the default.
    Localhost,
    /// Every interface: other hosts on the subnet see the node.
    Subnet,
}

/// The domain and the discovery range from `ROS_DOMAIN_ID`, `ROS_AUTOMATIC_DISCOVERY_RANGE`
/// (Jazzy) and `ROS_LOCALHOST_ONLY` (Humble); `open` (the `dds.open_discovery` parameter)
/// opens discovery whatever the environment says.
pub fn settings(env: impl Fn(&str) -> Option<String>, open: bool) -> Result<(u16, Discovery), DdsError> {
    let domain = match env("ROS_DOMAIN_ID").filter(|v| !v.trim().is_empty()) {
        Some(v) => v.trim().parse::<u16>().ok().filter(|d| *d <= 232).ok_or(DdsError::DomainId(v))?,
        None => 0,
    };
    let range =
        match env("ROS_AUTOMATIC_DISCOVERY_RANGE").map(|v| v.trim().to_ascii_uppercase()).filter(|v| !v.is_empty()) {
            None => Discovery::Localhost,
            Some(v) => match v.as_str() {
                "LOCALHOST" | "OFF" => Discovery::Localhost,
                "SUBNET" | "SYSTEM_DEFAULT" => Discovery::Subnet,
                _ => return Err(DdsError::DiscoveryRange(v)),
            },
        };
    // ROS_LOCALHOST_ONLY=1 (Humble's switch) keeps it local even if the range says otherwise.
    let localhost_only = env("ROS_LOCALHOST_ONLY").is_some_and(|v| v.trim() == "1");
    let discovery = if open {
        Discovery::Subnet
    } else if localhost_only {
        Discovery::Localhost
    } else {
        range
    };
    Ok((domain, discovery))
}

/// Whether this process sits in a network namespace whose only interface is `lo`
/// (`/proc/self/net/dev` lists this process's namespace; /sys/class/net the host's).
pub fn private_network() -> bool {
    let Ok(dev) = std::fs::read_to_string("/proc/self/net/dev") else { return false };
    let names: Vec<&str> = dev.lines().skip(2).filter_map(|l| l.split(':').next()).map(str::trim).collect();
    names == ["lo"]
}

/// A ros2-client context on a participant built for `discovery`.
pub fn context(domain: u16, discovery: Discovery) -> Result<ros2_client::Context, DdsError> {
    let builder = rustdds::DomainParticipantBuilder::new(domain);
    let builder = match discovery {
        Discovery::Localhost => builder.with_only_networks([Ipv4Addr::LOCALHOST]),
        Discovery::Subnet => {
            tracing::warn!("DDS discovery is open to the subnet (domain {domain}): other hosts can see this node");
            builder
        }
    };
    crate::pipeline::priority::at_force_loop_priority("the DDS participant", || {
        let participant = builder.build().map_err(|e| DdsError::Participant(e.to_string()))?;
        ros2_client::Context::from_domain_participant(participant).map_err(|e| DdsError::Participant(e.to_string()))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env<'a>(pairs: &'a [(&'a str, &'a str)]) -> impl Fn(&str) -> Option<String> + 'a {
        move |name| pairs.iter().find(|(n, _)| *n == name).map(|(_, v)| (*v).to_owned())
    }

    #[test]
    fn discovery_stays_on_loopback_unless_asked() {
        assert_eq!(settings(env(&[]), false), Ok((0, Discovery::Localhost)));
        assert_eq!(settings(env(&[("ROS_DOMAIN_ID", "42")]), false), Ok((42, Discovery::Localhost)));
        assert_eq!(settings(env(&[("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")]), false), Ok((0, Discovery::Subnet)));
        assert_eq!(
            settings(env(&[("ROS_AUTOMATIC_DISCOVERY_RANGE", "localhost")]), false),
            Ok((0, Discovery::Localhost))
        );
        assert_eq!(
            settings(env(&[("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET"), ("ROS_LOCALHOST_ONLY", "1")]), false),
            Ok((0, Discovery::Localhost))
        );
        assert_eq!(settings(env(&[]), true), Ok((0, Discovery::Subnet)));
        assert_eq!(settings(env(&[("ROS_DOMAIN_ID", "300")]), false), Err(DdsError::DomainId("300".into())));
        assert_eq!(settings(env(&[("ROS_DOMAIN_ID", "x")]), false), Err(DdsError::DomainId("x".into())));
        assert!(matches!(
            settings(env(&[("ROS_AUTOMATIC_DISCOVERY_RANGE", "WIDE")]), false),
            Err(DdsError::DiscoveryRange(_))
        ));
    }
}
