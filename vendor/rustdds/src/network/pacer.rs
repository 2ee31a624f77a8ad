//! Pacing of fragmented samples (a patch of defvol's, see `vendor/README.md`).
//!
//! A large sample's DATAFRAG datagrams used to leave back to back: a 300 KB image
//! is five 64 KiB datagrams on loopback, more than a receiver's default socket
//! buffer (Linux `net.core.rmem_default`, 208 KiB) holds, so a receiver that does
//! not read between two of them loses the whole best-effort sample. A token
//! bucket shared by the participant's writers lets a burst through at once and
//! spaces the rest, as Fast DDS's and Cyclone DDS's flow controllers do.

use std::time::{Duration, Instant};

/// Bytes a burst may carry at once: one loopback datagram, so that a default
/// receive buffer (three of them) has room for two more while its reader waits
/// for the CPU.
pub const BURST_BYTES: usize = 64 * 1024;

/// The rate the bucket refills at unless `RATE_VARIABLE` says otherwise: 32 MiB/s,
/// a loopback datagram every 2 ms.
pub const RATE_BYTES_PER_SECOND: f64 = 32.0 * 1024.0 * 1024.0;

/// The environment variable that sets the rate in bytes per second (0: no pacing).
pub const RATE_VARIABLE: &str = "RUSTDDS_PACING_RATE";

/// What a receive buffer is charged for a datagram besides its bytes (Linux counts
/// the socket buffer's true size: about 900 bytes more for a 1,400-byte datagram).
pub const DATAGRAM_OVERHEAD_BYTES: usize = 1024;

/// A held-back send resumes once the bucket holds this much, so that small
/// (path-MTU) datagrams go in batches, not one timer wake each.
pub const RESUME_BYTES: usize = 32 * 1024;

/// A token bucket over the bytes of fragmented samples; a rate of 0 lets all pass.
#[derive(Debug)]
pub struct Pacer {
  burst: f64,
  rate: f64,
  tokens: f64,
  refilled: Instant,
}

impl Default for Pacer {
  fn default() -> Self {
    let rate = match std::env::var(RATE_VARIABLE) {
      Err(_) => RATE_BYTES_PER_SECOND,
      Ok(text) => text.trim().parse::<f64>().ok().filter(|r| r.is_finite() && *r >= 0.0).unwrap_or_else(|| {
        log::warn!("{RATE_VARIABLE}={text:?} is no rate in bytes per second; pacing at {RATE_BYTES_PER_SECOND}");
        RATE_BYTES_PER_SECOND
      }),
    };
    Self::new(BURST_BYTES, rate)
  }
}

impl Pacer {
  pub fn new(burst_bytes: usize, rate_bytes_per_second: f64) -> Self {
    Self {
      burst: burst_bytes as f64,
      rate: rate_bytes_per_second,
      tokens: burst_bytes as f64,
      refilled: Instant::now(),
    }
  }

  /// Takes a datagram of `bytes` from the bucket if it holds them (one larger
  /// than the burst passes once the bucket is full), else says how long until
  /// it holds them or `RESUME_BYTES`, whichever is more.
  pub fn admit(&mut self, bytes: usize, now: Instant) -> Result<(), Duration> {
    if self.rate == 0.0 {
      return Ok(());
    }
    let elapsed = now.saturating_duration_since(self.refilled).as_secs_f64();
    self.tokens = (self.tokens + elapsed * self.rate).min(self.burst);
    self.refilled = now;
    let cost = (bytes + DATAGRAM_OVERHEAD_BYTES) as f64;
    if self.tokens >= cost.min(self.burst) {
      self.tokens -= cost;
      Ok(())
    } else {
      let resume = cost.max(RESUME_BYTES as f64).min(self.burst);
      // Rounded up, so that the bucket holds them when the wait is over.
      let nanos = ((resume - self.tokens) / self.rate * 1e9).ceil();
      Err(Duration::from_nanos(nanos as u64))
    }
  }
}

#[cfg(test)]
mod tests {
  use super::*;

  const KIB: usize = 1024;

  #[test]
  fn a_burst_passes_and_the_rest_waits_for_the_rate() {
    let start = Instant::now();
    let mut pacer = Pacer::new(130 * KIB, 64.0 * 1024.0 * KIB as f64);
    assert!(pacer.admit(64 * KIB, start).is_ok());
    assert!(pacer.admit(64 * KIB, start).is_ok());
    // 65 KiB charged (the datagram and its overhead) at 64 MiB/s is 65/65536 s.
    let wait = pacer.admit(64 * KIB, start).unwrap_err();
    assert!((wait.as_secs_f64() - 65.0 / 65536.0).abs() < 1e-9, "{wait:?}");
    assert!(pacer.admit(64 * KIB, start + wait).is_ok());
  }

  #[test]
  fn small_datagrams_resume_in_batches() {
    let start = Instant::now();
    let mut pacer = Pacer::new(64 * KIB, 1024.0 * KIB as f64);
    let mut sent = 0;
    while pacer.admit(1400, start).is_ok() {
      sent += 1;
    }
    // 64 KiB takes 27 datagrams charged 2,424 bytes each.
    assert_eq!(sent, 27);
    let wait = pacer.admit(1400, start).unwrap_err();
    let left = 64.0 * 1024.0 - 27.0 * 2424.0;
    assert!((wait.as_secs_f64() - (32.0 * 1024.0 - left) / (1024.0 * 1024.0)).abs() < 1e-9, "{wait:?}");
  }

  #[test]
  fn a_rate_of_zero_lets_all_pass() {
    let start = Instant::now();
    let mut pacer = Pacer::new(64 * KIB, 0.0);
    assert!((0..1000).all(|_| pacer.admit(64 * KIB, start).is_ok()));
  }

  #[test]
  fn a_datagram_larger_than_the_burst_passes_from_a_full_bucket() {
    let start = Instant::now();
    let mut pacer = Pacer::new(64 * KIB, 64.0 * KIB as f64);
    assert!(pacer.admit(200 * KIB, start).is_ok());
    // The bucket went 137 KiB below zero (the datagram's 201 KiB charged); it
    // refills at 64 KiB per second up to the 32 KiB a resume waits for.
    let wait = pacer.admit(10, start).unwrap_err();
    assert!((wait.as_secs_f64() - (137.0 + 32.0) / 64.0).abs() < 1e-9, "{wait:?}");
  }
}
