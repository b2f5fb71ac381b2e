//! Reading back what leaves the node without stalling the next frame: a small ring of staging
//! buffers. A frame records its copies into a free slot ([`ReadbackRing::record`]), is submitted,
//! and the slot is mapped asynchronously ([`ReadbackRing::submitted`]); the render thread goes on
//! with the next frame and collects mapped slots when it has nothing else to do
//! ([`ReadbackRing::poll`], [`ReadbackRing::wait_oldest`]). Slots are delivered in the order they
//! were recorded. A slot's staging buffer is kept and reused while it is large enough, so in a
//! steady state nothing is allocated.

use super::{GpuContext, GpuError};
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Copies start at multiples of this in a staging buffer (what texture copies need).
const ALIGN: u64 = 256;

/// What to copy into a slot.
pub enum Source<'a> {
    /// The first `len` bytes of a buffer (a multiple of 4).
    Buffer(&'a wgpu::Buffer, u64),
    /// A whole 2D texture of 4-byte texels (RGBA8); read back as tightly packed rows.
    Texture(&'a wgpu::Texture),
}

/// Where one source lies in the staging buffer.
#[derive(Clone, Copy, Debug)]
enum Part {
    Bytes { offset: u64, len: u64 },
    Rows { offset: u64, row: u32, padded: u32, rows: u32 },
}

impl Part {
    fn end(&self) -> u64 {
        match *self {
            Part::Bytes { offset, len } => offset + len,
            Part::Rows { offset, padded, rows, .. } => offset + padded as u64 * rows as u64,
        }
    }
}

/// A delivered read: its tag and the bytes of each source, in order.
pub struct Read<T> {
    pub tag: T,
    pub parts: Result<Vec<Vec<u8>>, GpuError>,
    /// From submit to when the read was collected (the GPU's work and the wait for it).
    pub latency: Duration,
}

type Mapped = Arc<Mutex<Option<Result<(), wgpu::BufferAsyncError>>>>;

struct InFlight<T> {
    tag: T,
    parts: Vec<Part>,
    /// Set by the map callback.
    mapped: Mapped,
    submission: Option<wgpu::SubmissionIndex>,
    submitted_at: Instant,
}

struct Slot<T> {
    buffer: Option<wgpu::Buffer>,
    busy: Option<InFlight<T>>,
    /// Recording order, for in-order delivery.
    sequence: u64,
}

/// The ring: at most `capacity` staging buffers.
pub struct ReadbackRing<T> {
    slots: Vec<Slot<T>>,
    capacity: usize,
    sequence: u64,
    ready: VecDeque<Read<T>>,
}

impl<T> ReadbackRing<T> {
    /// A ring of at most `capacity` (at least 1) staging buffers, made as they are first needed.
    pub fn new(capacity: usize) -> ReadbackRing<T> {
        ReadbackRing { slots: Vec::new(), capacity: capacity.max(1), sequence: 0, ready: VecDeque::new() }
    }

    /// Reads recorded and not yet delivered.
    pub fn in_flight(&self) -> usize {
        self.slots.iter().filter(|s| s.busy.is_some()).count()
    }

    /// Whether a slot is free for [`ReadbackRing::record`].
    pub fn has_free_slot(&self) -> bool {
        self.slots.len() < self.capacity || self.slots.iter().any(|s| s.busy.is_none())
    }

    /// Records copies of `sources` into a free slot (wait with [`ReadbackRing::wait_oldest`]
    /// first where there is none); returns the slot for [`ReadbackRing::submitted`].
    pub fn record(
        &mut self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        tag: T,
        sources: &[Source],
    ) -> Result<usize, GpuError> {
        let mut parts = Vec::with_capacity(sources.len());
        let mut end = 0u64;
        for s in sources {
            let offset = end.div_ceil(ALIGN) * ALIGN;
            let part = match s {
                Source::Buffer(_, len) => Part::Bytes { offset, len: *len },
                Source::Texture(t) => {
                    let row = 4 * t.width();
                    let padded = (row as u64).div_ceil(ALIGN) as u32 * ALIGN as u32;
                    Part::Rows { offset, row, padded, rows: t.height() }
                }
            };
            end = part.end();
            parts.push(part);
        }
        let size = end.max(4).div_ceil(ALIGN) * ALIGN;
        let index = match self.slots.iter().position(|s| s.busy.is_none()) {
            Some(i) => i,
            None if self.slots.len() < self.capacity => {
                self.slots.push(Slot { buffer: None, busy: None, sequence: 0 });
                self.slots.len() - 1
            }
            None => {
                return Err(GpuError::Readback(format!(
                    "all {} staging buffers are in flight (collect one first)",
                    self.capacity
                )))
            }
        };
        let slot = &mut self.slots[index];
        if slot.buffer.as_ref().is_none_or(|b| b.size() < size) {
            slot.buffer = Some(ctx.buffer(
                "readback",
                size,
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            ));
        }
        let staging = slot.buffer.as_ref().expect("made above");
        for (s, p) in sources.iter().zip(&parts) {
            match (s, *p) {
                (Source::Buffer(b, len), Part::Bytes { offset, .. }) => {
                    enc.copy_buffer_to_buffer(b, 0, staging, offset, *len)
                }
                (Source::Texture(t), Part::Rows { offset, padded, rows, .. }) => enc.copy_texture_to_buffer(
                    wgpu::TexelCopyTextureInfo {
                        texture: t,
                        mip_level: 0,
                        origin: wgpu::Origin3d::ZERO,
                        aspect: wgpu::TextureAspect::All,
                    },
                    wgpu::TexelCopyBufferInfo {
                        buffer: staging,
                        layout: wgpu::TexelCopyBufferLayout {
                            offset,
                            bytes_per_row: Some(padded),
                            rows_per_image: Some(rows),
                        },
                    },
                    t.size(),
                ),
                _ => unreachable!("parts follow sources"),
            }
        }
        self.sequence += 1;
        slot.sequence = self.sequence;
        slot.busy = Some(InFlight {
            tag,
            parts,
            mapped: Arc::new(Mutex::new(None)),
            submission: None,
            submitted_at: Instant::now(),
        });
        Ok(index)
    }

    /// The encoder holding slot `index`'s copies was submitted as `submission`: maps the slot.
    pub fn submitted(&mut self, index: usize, submission: wgpu::SubmissionIndex) {
        let slot = &mut self.slots[index];
        let (Some(buffer), Some(busy)) = (&slot.buffer, &mut slot.busy) else { return };
        busy.submission = Some(submission);
        busy.submitted_at = Instant::now();
        let mapped = busy.mapped.clone();
        buffer.map_async(wgpu::MapMode::Read, .., move |r| {
            *mapped.lock().unwrap_or_else(|e| e.into_inner()) = Some(r);
        });
    }

    /// Collects the mapped slots without blocking.
    pub fn poll(&mut self, ctx: &GpuContext) -> Result<(), GpuError> {
        ctx.device.poll(wgpu::PollType::Poll).map_err(|e| GpuError::Readback(e.to_string()))?;
        self.collect(ctx);
        Ok(())
    }

    /// Blocks until the oldest slot in flight is mapped, then collects; returns the time blocked.
    pub fn wait_oldest(&mut self, ctx: &GpuContext) -> Result<Duration, GpuError> {
        let start = Instant::now();
        let oldest = self.slots.iter().filter(|s| s.busy.is_some()).min_by_key(|s| s.sequence);
        if let Some(submission) = oldest.and_then(|s| s.busy.as_ref()).and_then(|b| b.submission.clone()) {
            ctx.device
                .poll(wgpu::PollType::Wait { submission_index: Some(submission), timeout: None })
                .map_err(|e| GpuError::Readback(e.to_string()))?;
        }
        self.collect(ctx);
        Ok(start.elapsed())
    }

    /// The reads delivered so far, in recording order.
    pub fn take_ready(&mut self) -> Vec<Read<T>> {
        self.ready.drain(..).collect()
    }

    /// Moves mapped slots, oldest first and in order, to the ready queue.
    fn collect(&mut self, ctx: &GpuContext) {
        loop {
            let Some(i) = (0..self.slots.len())
                .filter(|&i| self.slots[i].busy.is_some())
                .min_by_key(|&i| self.slots[i].sequence)
            else {
                return;
            };
            let slot = &mut self.slots[i];
            let state =
                slot.busy.as_ref().and_then(|b| b.mapped.lock().unwrap_or_else(|e| e.into_inner()).clone());
            let Some(state) = state else { return };
            let busy = slot.busy.take().expect("busy");
            let buffer = slot.buffer.as_ref().expect("a busy slot has a buffer");
            let parts = state
                .map_err(|e| GpuError::Readback(format!("mapping a staging buffer: {e}")))
                .and_then(|()| {
                    let view = buffer.get_mapped_range(..).map_err(|e| GpuError::Readback(e.to_string()))?;
                    let out = busy.parts.iter().map(|p| extract(&view, *p)).collect::<Vec<_>>();
                    drop(view);
                    Ok(out)
                });
            if let Ok(p) = &parts {
                ctx.traffic.read_back(p.iter().map(|b| b.len() as u64).sum());
            }
            buffer.unmap();
            self.ready.push_back(Read { tag: busy.tag, parts, latency: busy.submitted_at.elapsed() });
        }
    }
}

/// One source's bytes from the mapped staging buffer (texture rows without their padding).
fn extract(view: &[u8], part: Part) -> Vec<u8> {
    match part {
        Part::Bytes { offset, len } => view[offset as usize..(offset + len) as usize].to_vec(),
        Part::Rows { offset, row, padded, rows } => {
            let mut out = Vec::with_capacity(row as usize * rows as usize);
            for r in 0..rows as usize {
                let start = offset as usize + r * padded as usize;
                out.extend_from_slice(&view[start..start + row as usize]);
            }
            out
        }
    }
}
