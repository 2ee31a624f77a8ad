//! Large messages against the host's socket receive buffers. RustDDS sends the fragments of
//! a sample back to back (64 KiB datagrams on loopback), so a subscriber whose socket has the
//! kernel's default receive buffer (`net.core.rmem_default`, 212,992 bytes on Debian), as
//! Fast DDS's has (rclcpp's and rclpy's default middleware: RViz, rqt_image_view), drops
//! every sample whose burst overflows it; Cyclone DDS asks for 1 MiB itself. The
//! measurements are in docs/perf/journal.md.

/// A burst is taken whole when the buffer holds twice it (the kernel counts each datagram's
/// overhead, and the subscriber drains while the rest arrives).
const HEADROOM: usize = 2;

/// Where Linux says what buffer a socket gets unless it asks.
const RMEM_DEFAULT: &str = "/proc/sys/net/core/rmem_default";

/// The warning for outputs (`(topic, bytes per message)`) too large for a default receive
/// buffer of `rmem_default` bytes, naming the setting that would take them; none when all fit.
pub fn receive_buffer_warning(sizes: &[(&str, usize)], rmem_default: usize) -> Option<String> {
    let too_large: Vec<String> = sizes
        .iter()
        .filter(|(_, bytes)| bytes * HEADROOM > rmem_default)
        .map(|(topic, bytes)| format!("{topic} ({} KB)", bytes.div_ceil(1000)))
        .collect();
    let largest = sizes.iter().map(|(_, bytes)| *bytes).max()?;
    if too_large.is_empty() {
        return None;
    }
    let needed = (largest * HEADROOM).next_power_of_two().max(1 << 20);
    Some(format!(
        "messages on {} exceed what a subscriber's default socket receive buffer takes in one \
         burst (net.core.rmem_default = {rmem_default} bytes): subscribers on Fast DDS (RViz, \
         rqt_image_view, rclpy and rclcpp by default) will lose most of them. Raise it on the \
         subscribing hosts (`sysctl -w net.core.rmem_default={needed}`, with net.core.rmem_max at \
         least as large), or give Fast DDS a larger receiveBufferSize in its XML profile \
         (docs/node.md, Large messages)",
        too_large.join(", ")
    ))
}

/// Warns once, at start or reload, when this host's default buffer is too small for `sizes`.
pub fn warn_if_too_small(sizes: &[(&str, usize)]) {
    let rmem_default = std::fs::read_to_string(RMEM_DEFAULT).ok().and_then(|text| text.trim().parse().ok());
    match rmem_default {
        Some(rmem_default) => {
            if let Some(warning) = receive_buffer_warning(sizes, rmem_default) {
                tracing::warn!("{warning}");
            }
        }
        None => tracing::debug!("{RMEM_DEFAULT} unreadable: the receive-buffer check is skipped"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The journal's cases: what was lost at Debian's default buffer is warned of, what
    /// arrived at 1 MiB is not.
    #[test]
    fn what_was_lost_is_warned_of_and_what_arrived_is_not() {
        let sizes = [("deformed_mesh", 30_000), ("raycast/image", 307_200), ("dpcm/image", 196_608)];
        let warning = receive_buffer_warning(&sizes, 212_992).unwrap();
        assert!(warning.starts_with("messages on raycast/image (308 KB), dpcm/image (197 KB) exceed"), "{warning}");
        assert!(warning.contains("rmem_default = 212992") && warning.contains("rmem_default=1048576"), "{warning}");
        assert_eq!(receive_buffer_warning(&sizes, 1 << 20), None);
        assert_eq!(receive_buffer_warning(&[("deformed_mesh", 30_000)], 212_992), None);
        let big = receive_buffer_warning(&[("raycast/image", 1920 * 1080 * 4)], 1 << 20).unwrap();
        assert!(big.contains("rmem_default=16777216"), "{big}");
    }
}
