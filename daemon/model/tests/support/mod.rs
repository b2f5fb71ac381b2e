//! What the simulated-network tests share: the seeded PRNG and the virtual clock's events of the
//! model's LAN simulation.

pub use isowall_model::sim::lan::{Rng, Scheduled};
