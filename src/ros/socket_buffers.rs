//! Large messages against the host's socket receive buffers. RustDDS (as patched in
//! vendor/rustdds) paces the datagrams of a fragmented sample: a burst of
//! `rustdds::pacing::BURST_BYTES` at once, the rest at `RATE_BYTES_PER_SECOND`. A subscriber
//! whose socket has the kernel's default receive buffer (`net.core.rmem_default`), as Fast
//! DDS's has (rclcpp's and rclpy's default middleware: RViz, rqt_image_view), takes a large
//! image when that buffer holds a burst and the datagram after it; Debian's 212,992 bytes do.
//! The measurements are in docs/perf/journal.md.

use rustdds::pacing::{BURST_BYTES, DATAGRAM_OVERHEAD_BYTES};

/// The largest datagram RustDDS sends: loopback's 64 KiB path MTU.
const LARGEST_DATAGRAM: usize = 64 * 1024;

/// Where Linux says what buffer a socket gets unless it asks.
const RMEM_DEFAULT: &str = "/proc/sys/net/core/rmem_default";

/// The receive buffer a message of `bytes` needs: the message whole, or, when it is paced, a
/// burst and the datagram after it; each datagram charged its overhead.
fn buffer_needed(bytes: usize) -> usize {
    let arriving = bytes.min(BURST_BYTES + LARGEST_DATAGRAM);
    arriving + arriving.div_ceil(LARGEST_DATAGRAM) * DATAGRAM_OVERHEAD_BYTES
}

/// The warning for outputs (`(topic, bytes per message)`) too large for a default receive
/// buffer of `rmem_default` bytes, naming the setting that would take them; none when all fit.
pub fn receive_buffer_warning(sizes: &[(&str, usize)], rmem_default: usize) -> Option<String> {
    let too_large: Vec<(&str, usize)> =
        sizes.iter().copied().filter(|(_, bytes)| buffer_needed(*bytes) > rmem_default).collect();
    let needed = too_large.iter().map(|(_, bytes)| buffer_needed(*bytes)).max()?;
    let topics: Vec<String> =
        too_large.iter().map(|(topic, bytes)| format!("{topic} ({} KB)", bytes.div_ceil(1000))).collect();
    Some(format!(
        "messages on {} exceed what a subscriber's default socket receive buffer takes in one \
         burst (net.core.rmem_default = {rmem_default} bytes, {needed} needed): subscribers on \
         Fast DDS (RViz, rqt_image_view, rclpy and rclcpp by default) will lose most of them. \
         Raise it on the subscribing hosts (`sysctl -w net.core.rmem_default={}`, with \
         net.core.rmem_max at least as large), or give Fast DDS a larger receiveBufferSize in \
         its XML profile (docs/node.md, Large messages)",
        topics.join(", "),
        needed.next_power_of_two(),
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

    /// Debian's default buffer takes the paced images (the journal's delivery); a buffer of
    /// 128 KiB, as older kernels default to, does not take a burst and the datagram after it
    /// and is warned of, naming the next power of two above what is needed.
    #[test]
    fn a_buffer_that_cannot_take_a_paced_burst_is_warned_of() {
        let sizes = [("deformed_mesh", 30_000), ("raycast/image", 307_200), ("dpcm/image", 196_608)];
        assert_eq!(receive_buffer_warning(&sizes, 212_992), None);
        let warning = receive_buffer_warning(&sizes, 131_072).unwrap();
        assert!(warning.starts_with("messages on raycast/image (308 KB), dpcm/image (197 KB) exceed"), "{warning}");
        // A burst of 64 KiB and the datagram after it, each charged 1 KiB of overhead.
        assert!(warning.contains("rmem_default = 131072 bytes, 133120 needed"), "{warning}");
        assert!(warning.contains("rmem_default=262144"), "{warning}");
        assert_eq!(receive_buffer_warning(&[("deformed_mesh", 30_000)], 131_072), None);
        let small = receive_buffer_warning(&[("deformed_mesh", 30_000)], 16_384).unwrap();
        assert!(small.contains("31024 needed"), "{small}");
    }
}
