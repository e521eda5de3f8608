//! The renderer: the decoded mesh lit, fogged and coloured, with water and the other
//! vehicles, over a sky, into any texture view (a window's surface or an offscreen
//! texture: the same code).
//!
//! **Colour: a clipmap.** One `Rgba8UnormSrgb` 2D texture array, a layer per level of the
//! colour pyramid, each `S × S` texels (`S = min(W·T, cells)`, see
//! [`crate::color_cache`]), addressed toroidally: tiles are written where they land
//! (`queue.write_texture`, one call per tile, [`Renderer::update_colors`]) and the sampler
//! repeats, so the wrap costs nothing. Per level a uniform holds the window's origin and
//! the mask of tiles drawn. The fragment shader takes the screen-space level of detail
//! (the log2 of level-0 texels per pixel, from the derivatives of its cell coordinate) and
//! blends the two levels either side of it (trilinear), each the finest level at or above
//! it whose texels under the bilinear footprint are all resident, down to the coarsest,
//! which is resident from the join on. The texture needs
//! `levels × S²` texels (7 × 2048² × 4 B = 112 MiB at 16385² and W = 8); a layout that
//! does not fit the device (S past `max_texture_dimension_2d`, too many layers) is drawn
//! grey rather than failing.
//!
//! **Light: normals per pixel** ([`normals`]): a second clipmap of the same shape holds
//! each cell's normal (2 bytes a texel), streamed with the colour; the terrain is lit with
//! it wherever a tile has come, faded in over half a second, and with the vertex normal
//! (from the cut, [`vertices`]) elsewhere. So the light on a slope does not change when the
//! cut under it does.

mod buffer;
mod gpu;
pub(crate) mod math;
pub mod morph;
mod normals;
mod pipelines;
pub mod vertices;

use anyhow::{Context, Result};
use roam_protocol::tiles::ColorLayout;
use wgpu::util::DeviceExt;

use crate::color_cache::{ColorUpdate, LevelState, MASK_WORDS, layer_side};

use buffer::Buffer;
pub use gpu::{Gpu, NO_ADAPTER, configure_surface, native_max_texture};
pub use morph::{MORPH_MIN_TICKS, MORPH_PX_PER_TICK, MORPH_TICKS, Morph, MorphView};
pub use normals::{FADE_S, fade_byte};
pub use vertices::{TerrainUpdate, TerrainVertices};

/// What does not change during a session: the map's scales, sun, fog, water and colours.
#[derive(Clone, Debug)]
pub struct Scene {
    pub levels: u32,
    pub h_scale: f64,
    pub v_scale: f64,
    pub sun_dir: [f32; 3],
    pub sun_color: [u8; 3],
    pub fog_density: f32,
    pub fog_color: [u8; 3],
    /// World height of the water surface, if the map has one.
    pub water_level: Option<f32>,
    /// The colour pyramid's layout (the texels come by [`Renderer::update_colors`]).
    pub color: ColorLayout,
}

impl Scene {
    /// The scene a server's welcome describes.
    pub fn of(welcome: &roam_protocol::messages::Welcome) -> Scene {
        Scene {
            levels: u32::from(welcome.levels),
            h_scale: welcome.h_scale,
            v_scale: welcome.v_scale,
            sun_dir: welcome.sun_dir,
            sun_color: welcome.sun_color,
            fog_density: welcome.fog_density,
            fog_color: welcome.fog_color,
            water_level: welcome.water_level,
            color: welcome.color,
        }
    }

    /// The map's side in world units.
    pub fn world_size(&self) -> f32 {
        self.h_scale as f32 * (1u64 << self.levels.min(30)) as f32
    }
}

/// Where the camera is and what it sees.
#[derive(Clone, Copy, Debug)]
pub struct View {
    pub eye: [f32; 3],
    /// Heading convention: 0 faces south (+Z), 90 east (+X).
    pub yaw_deg: f32,
    /// Positive looks up.
    pub pitch_deg: f32,
    pub fov_y_deg: f32,
    /// Seconds, for the water's waves (a parameter: the same time draws the same picture).
    pub time_s: f32,
}

/// The viewer's switches.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Toggles {
    pub fog: bool,
    pub lighting: bool,
    pub wireframe: bool,
    /// The water surface, where the map has one.
    pub water: bool,
    /// The other vehicles' markers.
    pub vehicles: bool,
    /// The detail texture on the ground near the camera.
    pub detail: bool,
    /// Light per pixel from the normal tiles (off: the vertex normals alone, as before
    /// issue 24, for comparisons).
    pub normals: bool,
}

impl Default for Toggles {
    fn default() -> Self {
        Toggles {
            fog: true,
            lighting: true,
            wireframe: false,
            water: true,
            vehicles: true,
            detail: true,
            normals: true,
        }
    }
}

/// A vehicle to show.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Marker {
    /// Where it hovers (world units).
    pub pos: [f32; 3],
    pub heading_deg: f32,
    pub color: [u8; 3],
}

impl Marker {
    /// A colour of its own for vehicle `id`: hues spaced by the golden angle.
    pub fn color_of(id: u16) -> [u8; 3] {
        let hue = (f32::from(id) * 137.507_77).rem_euclid(360.0) / 60.0;
        let x = 1.0 - (hue.rem_euclid(2.0) - 1.0).abs();
        let (r, g, b) = match hue as u32 {
            0 => (1.0, x, 0.0),
            1 => (x, 1.0, 0.0),
            2 => (0.0, 1.0, x),
            3 => (0.0, x, 1.0),
            4 => (x, 0.0, 1.0),
            _ => (1.0, 0.0, x),
        };
        let q = |v: f32| (40.0 + v * 215.0) as u8;
        [q(r), q(g), q(b)]
    }
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Uniforms {
    view_proj: [[f32; 4]; 4],
    inv_view_proj: [[f32; 4]; 4],
    eye: [f32; 4],
    sun_dir: [f32; 4],
    sun_color: [f32; 4],
    fog_color: [f32; 4],
    params: [f32; 4],
    map: [f32; 4],
    output: [f32; 4],
}

/// One marker as the shader takes it.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Instance {
    place: [f32; 4],
    scale: [f32; 4],
    color: [u8; 4],
}

const _: () = assert!(std::mem::size_of::<Instance>().is_multiple_of(4));

/// The most colour levels the shader takes (a 32768-cell map in tiles of 4 has 14).
pub const MAX_COLOR_LEVELS: usize = 16;

/// One colour level as the shader takes it.
#[repr(C)]
#[derive(Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct ColorLevel {
    /// Window origin x0, z0 (tiles), the level's side (texels), unused.
    origin: [u32; 4],
    /// Tiles drawn: bit `(z mod W)·W + (x mod W)`.
    mask: [u32; MASK_WORDS],
}

/// The colour clipmap's uniform.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ColorLevels {
    /// Levels (0: no colour, grey), W, T, S.
    info: [u32; 4],
    level: [ColorLevel; MAX_COLOR_LEVELS],
}

/// Whether `layout`'s clipmap fits `limits` (and the shader's level count).
fn fits(layout: &ColorLayout, limits: &wgpu::Limits) -> bool {
    layout.check().is_ok()
        && usize::from(layout.levels) <= MAX_COLOR_LEVELS
        && layer_side(layout) <= limits.max_texture_dimension_2d
        && u32::from(layout.levels) <= limits.max_texture_array_layers
}

/// Draws a scene's meshes.
pub struct Renderer {
    pipelines: pipelines::Pipelines,
    uniforms: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    terrain: Buffer,
    model: wgpu::Buffer,
    model_count: u32,
    instances: Buffer,
    markers: Vec<Marker>,
    depth: Option<(wgpu::Texture, wgpu::TextureView, (u32, u32))>,
    scene: Scene,
    /// The terrain drawn, as built by [`Renderer::set_mesh`] or kept by
    /// [`Renderer::apply`].
    scratch: TerrainVertices,
    terrain_triangles: usize,
    /// The format drawn into.
    format: wgpu::TextureFormat,
    /// The target format does not encode sRGB: the shader does.
    encode_srgb: bool,
    /// The colour clipmap (a layer per level) and its uniform; `None` when the layout does
    /// not fit the device (drawn grey).
    colors: Option<wgpu::Texture>,
    color_uniform: wgpu::Buffer,
    color_levels: ColorLevels,
    /// The normal clipmap beside it, and its tiles' fades.
    normals: normals::NormalMaps,
}

const DEPTH: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Near plane, world units.
pub(crate) const NEAR: f32 = 0.5;

/// An sRGB colour as linear RGBA bytes (the shader works in linear light).
fn linear_rgba(c: [u8; 3]) -> [u8; 4] {
    let q = |v: u8| (srgb_to_linear(v) * 255.0).round() as u8;
    [q(c[0]), q(c[1]), q(c[2]), 255]
}

fn srgb_to_linear(c: u8) -> f32 {
    let c = f32::from(c) / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

impl Renderer {
    /// A renderer drawing into textures of `format`.
    pub fn new(gpu: &Gpu, format: wgpu::TextureFormat, scene: Scene) -> Renderer {
        let device = &gpu.device;
        let layout = scene.color;
        let fit = fits(&layout, &device.limits());
        let (side, layers) = if fit {
            (layer_side(&layout), u32::from(layout.levels))
        } else {
            (1, 1)
        };
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("colour clipmap"),
            size: wgpu::Extent3d {
                width: side,
                height: side,
                depth_or_array_layers: layers,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8UnormSrgb,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let mut color_levels = ColorLevels {
            info: [0; 4],
            level: [ColorLevel::default(); MAX_COLOR_LEVELS],
        };
        if fit {
            color_levels.info = [
                u32::from(layout.levels),
                u32::from(layout.window),
                layout.tile,
                side,
            ];
            for l in 0..layout.levels {
                color_levels.level[usize::from(l)].origin[2] = layout.side(l);
            }
        }
        let color_uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("colour levels"),
            contents: bytemuck::bytes_of(&color_levels),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        });
        let uniforms = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("uniforms"),
            size: std::mem::size_of::<Uniforms>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let normals = normals::NormalMaps::new(device, fit, side, layers);
        let (pipelines, bind_group) = pipelines::Pipelines::new(
            device,
            format,
            &uniforms,
            (&texture, &color_uniform),
            (normals.texture(), normals.uniform()),
        );
        let model_vertices = vertices::marker_model();
        let model = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("marker model"),
            contents: bytemuck::cast_slice(&model_vertices),
            usage: wgpu::BufferUsages::VERTEX,
        });
        Renderer {
            pipelines,
            uniforms,
            bind_group,
            terrain: Buffer::new("terrain"),
            model,
            model_count: model_vertices.len() as u32,
            instances: Buffer::new("markers"),
            markers: Vec::new(),
            depth: None,
            scene,
            scratch: TerrainVertices::default(),
            terrain_triangles: 0,
            encode_srgb: !format.is_srgb(),
            format,
            colors: fit.then_some(texture),
            color_uniform,
            color_levels,
            normals,
        }
    }

    /// Bytes of the colour and normal clipmaps on the GPU (4 and 2 a texel).
    pub fn clipmap_bytes(&self) -> (u64, u64) {
        let colors = self.colors.as_ref().map_or(0, |t| {
            let s = t.size();
            u64::from(s.width) * u64::from(s.height) * u64::from(s.depth_or_array_layers) * 4
        });
        let normals = if self.colors.is_some() {
            self.normals.bytes()
        } else {
            0
        };
        (colors, normals)
    }

    /// Sets the renderer's clock to `time_s` (a frame's `View::time_s`) without drawing:
    /// tiles written next are stamped with it, and their normals fade in from then. Two
    /// renderers given the same times and updates fade alike, whichever draws.
    pub fn set_time(&mut self, gpu: &Gpu, time_s: f32) {
        self.normals.frame(gpu, time_s);
    }

    /// Writes a colour update ([`crate::color_cache::ColorCache::drain`]): each tile into
    /// its layer (colour, normals), then every level's window and masks. Ignored when the
    /// layout did not fit.
    pub fn update_colors(&mut self, gpu: &Gpu, update: &ColorUpdate) {
        let Some(texture) = &self.colors else {
            return;
        };
        let side = self.color_levels.info[3];
        let layers = self.color_levels.info[0];
        for u in &update.uploads {
            // A cache of another layout is a caller's bug: never a wgpu validation panic.
            let fits = u.layer < layers
                && u.x + u.size <= side
                && u.y + u.size <= side
                && u.texels.len() as u64 == u64::from(u.size) * u64::from(u.size) * 4;
            if !fits {
                continue;
            }
            gpu.queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture,
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
                    bytes_per_row: Some(u.size * 4),
                    rows_per_image: Some(u.size),
                },
                wgpu::Extent3d {
                    width: u.size,
                    height: u.size,
                    depth_or_array_layers: 1,
                },
            );
        }
        self.normals.update(gpu, &update.normals, &update.levels);
        for (l, state) in update.levels.iter().take(layers as usize).enumerate() {
            let LevelState { origin, drawn, .. } = *state;
            let level = &mut self.color_levels.level[l];
            level.origin[0] = origin[0];
            level.origin[1] = origin[1];
            level.mask = drawn;
        }
        gpu.queue.write_buffer(
            &self.color_uniform,
            0,
            bytemuck::bytes_of(&self.color_levels),
        );
    }

    /// The format it draws into.
    pub fn format(&self) -> wgpu::TextureFormat {
        self.format
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Triangles of the terrain drawn.
    pub fn triangles(&self) -> usize {
        self.terrain_triangles
    }

    /// Replaces the terrain drawn with `mesh` from the codec (grid vertices, heights,
    /// triangles).
    pub fn set_mesh(&mut self, gpu: &Gpu, mesh: &roam_protocol::Mesh) {
        let mut scratch = std::mem::take(&mut self.scratch);
        scratch.build(&self.scene, mesh);
        self.upload(gpu, &scratch);
        self.scratch = scratch;
    }

    /// Replaces the terrain drawn with vertices built elsewhere (on the network thread).
    pub fn upload(&mut self, gpu: &Gpu, terrain: &TerrainVertices) {
        self.terrain.write(
            gpu,
            bytemuck::cast_slice(&terrain.corners),
            terrain.corners.len(),
        );
        self.terrain_triangles = terrain.triangles();
    }

    /// Uploads what changed in `terrain` since its last upload (the slots a frame
    /// rewrote, [`TerrainVertices::take_ranges`]), or the whole when the buffer has no
    /// room for it.
    pub fn upload_dirty(&mut self, gpu: &Gpu, terrain: &mut TerrainVertices) {
        let len = terrain.corners.len();
        let mut whole = false;
        let buffer = &mut self.terrain;
        terrain.take_ranges(|first, corners| {
            let offset = (first * std::mem::size_of::<vertices::Vertex>()) as u64;
            whole |= !buffer.write_at(gpu, offset, bytemuck::cast_slice(corners), len);
        });
        if whole {
            self.terrain
                .write(gpu, bytemuck::cast_slice(&terrain.corners), len);
        }
        self.terrain_triangles = terrain.triangles();
    }

    /// Applies `update` (from the network thread's vertices) to the copy drawn, and
    /// uploads what it changed.
    pub fn apply(&mut self, gpu: &Gpu, update: &TerrainUpdate) {
        let mut copy = std::mem::take(&mut self.scratch);
        copy.apply(update);
        self.upload_dirty(gpu, &mut copy);
        self.scratch = copy;
    }

    /// The vehicles to show (besides the one the camera rides).
    pub fn set_markers(&mut self, markers: &[Marker]) {
        self.markers.clear();
        self.markers.extend_from_slice(markers);
    }

    /// Draws the sky, the terrain, the vehicles and the water into `target` (`size` pixels).
    pub fn render(
        &mut self,
        gpu: &Gpu,
        target: &wgpu::TextureView,
        size: (u32, u32),
        view: &View,
        toggles: Toggles,
    ) {
        if self.depth.as_ref().is_none_or(|d| d.2 != size) {
            let texture = target_texture(gpu, "depth", size, DEPTH, wgpu::TextureUsages::empty());
            let view = texture.create_view(&Default::default());
            self.depth = Some((texture, view, size));
        }
        let aspect = size.0 as f32 / size.1.max(1) as f32;
        let fov = view.fov_y_deg.clamp(1.0, 179.0).to_radians();
        let view_proj = math::view_proj(view, size);
        let inv_view_proj = math::mul(
            math::look_inverse(view.eye, view.yaw_deg, view.pitch_deg),
            math::perspective_inverse(fov, aspect, NEAR),
        );
        let s = &self.scene;
        let lin = |c: [u8; 3]| {
            [
                srgb_to_linear(c[0]),
                srgb_to_linear(c[1]),
                srgb_to_linear(c[2]),
                1.0,
            ]
        };
        let flag = |b: bool| f32::from(u8::from(b));
        let u = Uniforms {
            view_proj,
            inv_view_proj,
            eye: [view.eye[0], view.eye[1], view.eye[2], 1.0],
            sun_dir: [s.sun_dir[0], s.sun_dir[1], s.sun_dir[2], 0.0],
            sun_color: lin(s.sun_color),
            fog_color: lin(s.fog_color),
            params: [
                s.fog_density,
                flag(toggles.fog),
                flag(toggles.lighting),
                flag(toggles.wireframe),
            ],
            map: [
                s.world_size(),
                s.water_level.unwrap_or(0.0),
                view.time_s,
                flag(toggles.detail),
            ],
            output: [flag(self.encode_srgb), flag(toggles.normals), 0.0, 0.0],
        };
        gpu.queue
            .write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&u));
        self.normals.frame(gpu, view.time_s);
        let markers = toggles.vehicles && !self.markers.is_empty();
        if markers {
            let instances: Vec<Instance> = self
                .markers
                .iter()
                .map(|m| {
                    // At least about ten pixels long however far: a marker, not a model.
                    let d = math::sub(m.pos, view.eye);
                    let dist = math::dot(d, d).sqrt();
                    let scale = (dist / 250.0).max(1.5);
                    Instance {
                        place: [m.pos[0], m.pos[1], m.pos[2], m.heading_deg],
                        scale: [scale, 0.0, 0.0, 0.0],
                        color: linear_rgba(m.color),
                    }
                })
                .collect();
            self.instances
                .write(gpu, bytemuck::cast_slice(&instances), instances.len());
        }
        let water = toggles.water && s.water_level.is_some();
        let mut encoder = gpu.device.create_command_encoder(&Default::default());
        {
            let depth = &self.depth.as_ref().expect("made above").1;
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("frame"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: target,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: depth,
                    depth_ops: Some(wgpu::Operations {
                        // Reversed depth: 0 is infinitely far.
                        load: wgpu::LoadOp::Clear(0.0),
                        store: wgpu::StoreOp::Store,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            let p = &self.pipelines;
            pass.set_bind_group(0, &self.bind_group, &[]);
            pass.set_pipeline(&p.sky);
            pass.draw(0..3, 0..1);
            if let Some((slice, count)) = self.terrain.slice() {
                pass.set_pipeline(&p.terrain);
                pass.set_vertex_buffer(0, slice);
                pass.draw(0..count, 0..1);
            }
            if markers && let Some((slice, count)) = self.instances.slice() {
                pass.set_pipeline(&p.markers);
                pass.set_vertex_buffer(0, self.model.slice(..));
                pass.set_vertex_buffer(1, slice);
                pass.draw(0..self.model_count, 0..count);
            }
            // Last: it is blended over what lies under it.
            if water {
                pass.set_pipeline(&p.water);
                pass.draw(0..6, 0..1);
            }
        }
        gpu.queue.submit([encoder.finish()]);
    }
}

/// A 2D texture to render into, of `size` pixels, with `usage` besides that.
pub(crate) fn target_texture(
    gpu: &Gpu,
    label: &str,
    size: (u32, u32),
    format: wgpu::TextureFormat,
    usage: wgpu::TextureUsages,
) -> wgpu::Texture {
    gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width: size.0,
            height: size.1,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | usage,
        view_formats: &[],
    })
}

/// Renders offscreen, into a texture of the renderer's format (RGBA8, sRGB-encoding or
/// not), and returns the RGBA pixels, row by row.
pub fn render_offscreen(
    gpu: &Gpu,
    renderer: &mut Renderer,
    size: (u32, u32),
    view: &View,
    toggles: Toggles,
) -> Result<Vec<u8>> {
    let format = renderer.format();
    let texture = target_texture(
        gpu,
        "offscreen",
        size,
        format,
        wgpu::TextureUsages::COPY_SRC,
    );
    let target = texture.create_view(&Default::default());
    renderer.render(gpu, &target, size, view, toggles);
    let row = (size.0 * 4).div_ceil(256) * 256;
    let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: u64::from(row * size.1),
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut encoder = gpu.device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: Some(size.1),
            },
        },
        wgpu::Extent3d {
            width: size.0,
            height: size.1,
            depth_or_array_layers: 1,
        },
    );
    gpu.queue.submit([encoder.finish()]);
    let slice = buffer.slice(..);
    slice.map_async(wgpu::MapMode::Read, |_| {});
    gpu.device
        .poll(wgpu::PollType::wait_indefinitely())
        .context("waiting for the GPU")?;
    let mapped = slice.get_mapped_range().context("reading the frame back")?;
    let mut pixels = Vec::with_capacity((size.0 * size.1 * 4) as usize);
    for y in 0..size.1 {
        let start = (y * row) as usize;
        pixels.extend_from_slice(&mapped[start..start + (size.0 * 4) as usize]);
    }
    Ok(pixels)
}

/// Writes RGBA pixels as a PNG.
pub fn write_png(path: &std::path::Path, size: (u32, u32), rgba: &[u8]) -> Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), size.0, size.1);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().context("writing the PNG header")?;
    w.write_image_data(rgba).context("writing the PNG")?;
    Ok(())
}

/// A plain scene for unit tests: overhead sun, no fog, no water.
#[cfg(test)]
pub(crate) fn test_scene(levels: u32, h_scale: f64, v_scale: f64) -> Scene {
    Scene {
        levels,
        h_scale,
        v_scale,
        sun_dir: [0.0, 1.0, 0.0],
        sun_color: [255; 3],
        fog_density: 0.0,
        fog_color: [0; 3],
        water_level: None,
        color: ColorLayout::new(1 << levels, 256, 8).expect("a valid layout"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_layout_beyond_the_device_is_drawn_grey() {
        let limits = wgpu::Limits::default();
        let ok = ColorLayout::new(1 << 15, 256, 8).expect("a valid layout");
        assert!(fits(&ok, &limits));
        let wide = ColorLayout::new(1 << 15, 256, 16).expect("a valid layout");
        assert!(!fits(&wide, &wgpu::Limits::downlevel_webgl2_defaults()));
        let tiny = ColorLayout::new(1 << 15, 1, 1).expect("a valid layout");
        assert_eq!(tiny.levels, 16);
        assert!(fits(&tiny, &limits));
        let odd = ColorLayout { levels: 17, ..tiny };
        assert!(!fits(&odd, &limits));
        assert_eq!(
            std::mem::size_of::<ColorLevels>(),
            16 + 48 * MAX_COLOR_LEVELS
        );
    }

    #[test]
    fn marker_colours_are_distinct_and_linear() {
        let a = Marker::color_of(0);
        let b = Marker::color_of(1);
        assert_ne!(a, b);
        assert_eq!(linear_rgba([255, 0, 128]), [255, 0, 55, 255]);
    }
}
