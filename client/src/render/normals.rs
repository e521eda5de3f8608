//! The terrain's normal maps on the GPU: a second clipmap beside the colour's (the same
//! layout, windows and toroidal addressing: [`crate::color_cache`]), one `Rg8Unorm` layer
//! per level holding each texel's two-byte normal code ([`roam_protocol::normals`]), and
//! the uniform of every tile's fade. The fragment shader lights each pixel with the normals
//! of the two levels either side of the screen's level of detail (trilinear), each the
//! finest level at or above it whose footprint has normals, blended over the coarser levels' and over the vertex normal by the tiles'
//! fades (`normal_at` in `shader.wgsl`): the light no longer depends on the cut drawn.
//!
//! Decisions:
//!
//! - **Fades, not pops**: a tile's normals fade in over [`FADE_S`] (0.5 s) from the moment
//!   its texels are written: the light under it moves from the vertex normal (or the
//!   coarser level's normals) to its own smoothly, and a finer level arriving fades over a
//!   coarser one the same way. Time is the frame's (`View::time_s`, the renderer reads no
//!   clock): a tile written between two frames arrived at the earlier one; tiles written
//!   before the first frame are shown whole (nothing was drawn to pop from).
//! - **The fade is a byte per tile in a uniform** (16 levels × 256 window slots = 4 KiB,
//!   within WebGL2's 16 KiB uniform blocks; no storage buffer in the fragment stage),
//!   computed on the CPU each frame from the arrival times and written only when it
//!   changed: the shader multiplies, it keeps no time. 0 is "no normals here" (a slot
//!   empty, dropped by a window move, or not yet written); the level's origin is the
//!   colour uniform's.
//! - **Memory**: `levels × S²` texels of 2 bytes, half the colour clipmap's: 6 MiB on
//!   kossou (1024², S = 1024, 3 levels), 56 MiB at 16385² with W = 8 (7 layers of 2048²).

use crate::color_cache::{LevelState, MASK_WORDS, Upload};

use super::{Gpu, MAX_COLOR_LEVELS};

/// Seconds a tile's normals take to fade in.
pub const FADE_S: f32 = 0.5;
/// Window slots a level has at most ([`roam_protocol::tiles::MAX_WINDOW`]²).
const SLOTS: usize = MASK_WORDS * 32;

/// The fades' uniform: a byte per (level, slot), level-major, four to a word.
#[repr(C)]
#[derive(Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
struct Fades {
    fade: [[u32; 4]; MAX_COLOR_LEVELS * SLOTS / 16],
}

const _: () = assert!(std::mem::size_of::<Fades>() == 4096);

/// The fade byte of a tile whose texels were written at `arrived` (`None`: before the
/// first frame), seen at `now`: 1 ..= 255 over [`FADE_S`].
pub fn fade_byte(arrived: Option<f32>, now: f32) -> u8 {
    let t = arrived.map_or(1.0, |a| ((now - a) / FADE_S).clamp(0.0, 1.0));
    (1.0 + t * 254.0).round() as u8
}

/// The normal clipmap, its fades' uniform and what they are made from.
pub(super) struct NormalMaps {
    texture: wgpu::Texture,
    uniform: wgpu::Buffer,
    /// The layout fits the device (else nothing is uploaded and every fade is 0).
    fit: bool,
    side: u32,
    layers: u32,
    /// Per level and slot: when its tile's texels were written (`None`: before the first
    /// frame).
    arrived: Vec<[Option<f32>; SLOTS]>,
    /// Per level: the slots whose normals the renderer has.
    drawn: Vec<[u32; MASK_WORDS]>,
    /// The time of the last frame drawn.
    clock: Option<f32>,
    /// The fades last written.
    written: Fades,
}

impl NormalMaps {
    /// Texture and uniform for `layers` layers of `side²` texels (`fit`), else a
    /// placeholder that draws nothing.
    pub(super) fn new(device: &wgpu::Device, fit: bool, side: u32, layers: u32) -> NormalMaps {
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("normal clipmap"),
            size: wgpu::Extent3d {
                width: side,
                height: side,
                depth_or_array_layers: layers,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rg8Unorm,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let written = Fades {
            fade: [[0; 4]; MAX_COLOR_LEVELS * SLOTS / 16],
        };
        let uniform = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("normal fades"),
            size: std::mem::size_of::<Fades>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let levels = if fit { layers as usize } else { 0 };
        NormalMaps {
            texture,
            uniform,
            fit,
            side,
            layers,
            arrived: vec![[None; SLOTS]; levels],
            drawn: vec![[0; MASK_WORDS]; levels],
            clock: None,
            written,
        }
    }

    pub(super) fn texture(&self) -> &wgpu::Texture {
        &self.texture
    }

    pub(super) fn uniform(&self) -> &wgpu::Buffer {
        &self.uniform
    }

    /// Bytes of the texture.
    pub(super) fn bytes(&self) -> u64 {
        u64::from(self.side).pow(2) * u64::from(self.layers) * 2
    }

    /// Writes `uploads` (each tile's codes into its layer, its arrival stamped with the
    /// last frame's time) and takes `levels`' normal masks.
    pub(super) fn update(&mut self, gpu: &Gpu, uploads: &[Upload], levels: &[LevelState]) {
        if !self.fit {
            return;
        }
        for u in uploads {
            // A cache of another layout is a caller's bug: never a wgpu validation panic.
            let fits = u.layer < self.layers
                && (u.slot as usize) < SLOTS
                && u.x + u.size <= self.side
                && u.y + u.size <= self.side
                && u.texels.len() as u64 == u64::from(u.size) * u64::from(u.size) * 2;
            if !fits {
                continue;
            }
            gpu.queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &self.texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d {
                        x: u.x,
                        y: u.y,
                        z: u.layer,
                    },
                    aspect: wgpu::TextureAspect::All,
                },
                &u.texels,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(u.size * 2),
                    rows_per_image: Some(u.size),
                },
                wgpu::Extent3d {
                    width: u.size,
                    height: u.size,
                    depth_or_array_layers: 1,
                },
            );
            self.arrived[u.layer as usize][u.slot as usize] = self.clock;
        }
        for (drawn, state) in self.drawn.iter_mut().zip(levels) {
            *drawn = state.normals;
        }
    }

    /// A frame at `now` (seconds): every tile's fade, written when it changed.
    pub(super) fn frame(&mut self, gpu: &Gpu, now: f32) {
        // Time that went backwards (another clock) must not hide tiles.
        if self.clock.is_some_and(|c| now < c) {
            for level in &mut self.arrived {
                for a in level.iter_mut().flatten() {
                    *a = a.min(now);
                }
            }
        }
        self.clock = Some(now);
        let mut fades = Fades {
            fade: [[0; 4]; MAX_COLOR_LEVELS * SLOTS / 16],
        };
        let words: &mut [u32] = bytemuck::cast_slice_mut(&mut fades.fade);
        for (l, (drawn, arrived)) in self.drawn.iter().zip(&self.arrived).enumerate() {
            for (b, &a) in arrived.iter().enumerate() {
                if drawn[b / 32] >> (b % 32) & 1 == 1 {
                    let i = l * SLOTS + b;
                    words[i / 4] |= u32::from(fade_byte(a, now)) << ((i % 4) * 8);
                }
            }
        }
        if fades != self.written {
            gpu.queue
                .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&fades));
            self.written = fades;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tile_fades_in_over_half_a_second() {
        assert_eq!(fade_byte(None, 0.0), 255);
        assert_eq!(fade_byte(Some(10.0), 10.0), 1);
        assert_eq!(fade_byte(Some(10.0), 10.25), 128);
        assert_eq!(fade_byte(Some(10.0), 10.5), 255);
        assert_eq!(fade_byte(Some(10.0), 99.0), 255);
        assert_eq!(fade_byte(Some(10.0), 9.0), 1);
        // Never 0 once written: 0 is "no normals".
        let mut last = 0;
        for k in 0..=60 {
            let b = fade_byte(Some(0.0), k as f32 / 100.0);
            assert!(b >= last.max(1), "{k}: {b}");
            last = b;
        }
    }
}
