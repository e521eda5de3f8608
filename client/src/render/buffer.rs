//! A vertex buffer that grows as needed and is otherwise reused (the terrain's, the
//! markers' instances).

use super::Gpu;
use super::vertices::Vertex;

/// A vertex buffer that grows as needed and is otherwise reused.
pub(super) struct Buffer {
    label: &'static str,
    buffer: Option<wgpu::Buffer>,
    count: u32,
}

impl Buffer {
    pub(super) fn new(label: &'static str) -> Buffer {
        Buffer {
            label,
            buffer: None,
            count: 0,
        }
    }

    pub(super) fn write(&mut self, gpu: &Gpu, bytes: &[u8], count: usize) {
        let need = bytes.len() as u64;
        if self.buffer.as_ref().is_none_or(|b| b.size() < need) {
            // Room for growth: meshes vary frame to frame.
            self.buffer = Some(
                gpu.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(self.label),
                    size: (need + need / 2)
                        .max(256)
                        .next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT),
                    usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                }),
            );
        }
        if let Some(b) = &self.buffer {
            gpu.queue.write_buffer(b, 0, bytes);
        }
        self.count = count as u32;
    }

    /// Writes `bytes` at `offset` (bytes) of a buffer of `count` vertices in all; false
    /// when the buffer is too small (the caller writes the whole instead).
    pub(super) fn write_at(&mut self, gpu: &Gpu, offset: u64, bytes: &[u8], count: usize) -> bool {
        let need = (count * std::mem::size_of::<Vertex>()) as u64;
        match &self.buffer {
            Some(b) if b.size() >= need => {
                gpu.queue.write_buffer(b, offset, bytes);
                self.count = count as u32;
                true
            }
            _ => false,
        }
    }

    pub(super) fn slice(&self) -> Option<(wgpu::BufferSlice<'_>, u32)> {
        let b = self.buffer.as_ref().filter(|_| self.count > 0)?;
        Some((b.slice(..), self.count))
    }
}
