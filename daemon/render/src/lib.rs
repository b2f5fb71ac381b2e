//! Isowall's renderers. [`gpu`] is the wgpu compute ray-caster (one kernel per WGSL file in
//! `shaders/`, see [`shaders`]); [`reference`] is the exact CPU renderer (f64, cubic roots per
//! cell) that the GPU is tested against. Both produce a [`Frame`] for a
//! [`View`](isowall_model::View) of a volume. Nothing here touches the network.

pub mod denoise;
pub mod environment;
pub mod frame;
pub mod frame_plan;
pub mod gpu;
pub mod output;
pub mod reference;
pub mod reproject;
pub mod sampling;
pub mod shaders;

pub use frame::Frame;
