//! The renderer on a software adapter (lavapipe where there is no GPU): fog, lighting,
//! wireframe, the sky, a reference image, and the colour clipmap (the finest resident
//! level drawn where it is resident, a coarser one elsewhere).

use std::sync::Arc;

use roam_client::color_cache::ColorCache;
use roam_client::render::{self, Gpu, Renderer, Scene, Toggles, View};
use roam_protocol::tiles::ColorLayout;
use roam_server::Terrain;
use roam_server::terrain::dataset;
use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::camera::Camera;
use roam_server::tessellate::{Limits, Mesh, Scales, Tessellator};

const SIZE: (u32, u32) = (192, 108);

fn load(name: &str) -> Arc<Terrain> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../data")
        .join(name);
    Arc::new(dataset::load(&dir, &mut |_, _| {}).expect("bundled"))
}

fn scene(t: &Terrain) -> Scene {
    let m = &t.map;
    Scene {
        levels: t.heights.levels(),
        h_scale: m.h_scale,
        v_scale: m.v_scale,
        sun_dir: m.sun_dir.map(|v| v as f32),
        sun_color: m.sun_color,
        // Thick fog, so a small test image shows it.
        fog_density: 4.0 / t.world_size() as f32,
        fog_color: m.fog_color,
        water_level: m.water_level.map(|w| w as f32),
        color: layout(t),
    }
}

/// The bundled map's colour layout as a server sends it (one tile of 256²).
fn layout(t: &Terrain) -> ColorLayout {
    ColorLayout::new(color(t).cells(), 256, 8).expect("a valid layout")
}

/// The colour map of a bundled data set (`dataset::load` always reads it).
fn color(t: &Terrain) -> &roam_server::terrain::dataset::ColorMap {
    t.color
        .as_ref()
        .expect("dataset::load reads the colour map")
}

/// A renderer with the terrain's whole colour map resident (or a uniform grey).
fn renderer(gpu: &Gpu, t: &Terrain, uniform_color: bool, format: wgpu::TextureFormat) -> Renderer {
    let rgb: Vec<u8> = if uniform_color {
        vec![120; color(t).rgb().len() * 3]
    } else {
        color(t).rgb().iter().flatten().copied().collect()
    };
    let mut cache = ColorCache::whole(layout(t), &rgb).expect("the map's own texels");
    let mut r = Renderer::new(gpu, format, scene(t));
    r.update_colors(gpu, &cache.drain(usize::MAX));
    r
}

/// The view from a point over the map's west edge, level, looking east across it, and the
/// tessellation for it.
fn view_and_mesh(t: &Terrain) -> (View, roam_protocol::Mesh) {
    let size = t.world_size();
    let ground = t.world_height(0, t.heights.size() / 2);
    let eye = [size * 0.02, ground + size * 0.03, size * 0.5];
    let cam = Camera {
        eye,
        yaw_deg: 90.0,
        pitch_deg: 0.0,
        fov_y_deg: 60.0,
        width: SIZE.0,
        height: SIZE.1,
    };
    let vt = VarianceTree::build(&t.heights, 1, &mut |_, _| {});
    let mut tess = Tessellator::new(t.heights.side());
    let mut mesh = Mesh::default();
    let scales = Scales {
        h: t.map.h_scale,
        v: t.map.v_scale,
    };
    tess.tessellate(
        &t.heights,
        &vt,
        scales,
        &cam,
        Limits {
            budget: 20_000,
            threshold_px: 0.0,
            fog_density: 0.0,
            guard_deg: 0.0,
        },
        &mut mesh,
    );
    let heights = mesh
        .vertices
        .iter()
        .map(|v| t.heights.get(u32::from(v[0]), u32::from(v[1])))
        .collect();
    let view = View {
        eye: eye.map(|v| v as f32),
        yaw_deg: 90.0,
        pitch_deg: 0.0,
        fov_y_deg: 60.0,
        time_s: 0.0,
    };
    (
        view,
        roam_protocol::Mesh {
            vertices: mesh.vertices,
            heights,
            indices: mesh.indices,
        },
    )
}

fn gpu() -> Gpu {
    Gpu::headless().unwrap_or_else(|e| panic!("{e:#}"))
}

fn draw(gpu: &Gpu, t: &Terrain, uniform: bool, toggles: Toggles) -> Vec<[u8; 3]> {
    let (view, mesh) = view_and_mesh(t);
    let mut r = renderer(gpu, t, uniform, wgpu::TextureFormat::Rgba8UnormSrgb);
    r.set_mesh(gpu, &mesh);
    let rgba = render::render_offscreen(gpu, &mut r, SIZE, &view, toggles).expect("renders");
    rgba.chunks(4).map(|p| [p[0], p[1], p[2]]).collect()
}

fn row(img: &[[u8; 3]], y: u32) -> &[[u8; 3]] {
    &img[(y * SIZE.0) as usize..((y + 1) * SIZE.0) as usize]
}

fn dist(a: [u8; 3], b: [u8; 3]) -> f64 {
    (0..3)
        .map(|k| (f64::from(a[k]) - f64::from(b[k])).abs())
        .sum()
}

fn mean_dist(px: &[[u8; 3]], c: [u8; 3]) -> f64 {
    px.iter().map(|&p| dist(p, c)).sum::<f64>() / px.len() as f64
}

#[test]
fn sky_above_the_horizon_at_level_pitch() {
    let gpu = gpu();
    let t = load("synth-257");
    let img = draw(&gpu, &t, false, Toggles::default());
    for y in 0..5 {
        for p in row(&img, y) {
            assert!(p[2] > p[0], "row {y}: sky is blue, got {p:?}");
        }
    }
    // The sky is brighter and bluer towards the top.
    let (top, high) = (row(&img, 0)[0], row(&img, 40)[0]);
    assert!(
        top[2] >= high[2] && dist(top, high) > 3.0,
        "{top:?} {high:?}"
    );
}

#[test]
fn fog_moves_distant_ground_towards_the_fog_colour() {
    let gpu = gpu();
    let t = load("synth-257");
    let fog = t.map.fog_color;
    let on = draw(&gpu, &t, false, Toggles::default());
    let off = draw(
        &gpu,
        &t,
        false,
        Toggles {
            fog: false,
            ..Toggles::default()
        },
    );
    // The rows just below the horizon are the farthest ground.
    let band =
        |img: &[[u8; 3]]| -> Vec<[u8; 3]> { (56..64).flat_map(|y| row(img, y).to_vec()).collect() };
    let (d_on, d_off) = (mean_dist(&band(&on), fog), mean_dist(&band(&off), fog));
    assert!(d_on + 10.0 < d_off, "fog on {d_on}, off {d_off}");
}

#[test]
fn lighting_off_shades_flat_and_wireframe_shows_lines() {
    let gpu = gpu();
    let t = load("synth-257");
    let flat = Toggles {
        fog: false,
        lighting: false,
        wireframe: false,
        water: false,
        vehicles: false,
        detail: false,
        normals: true,
    };
    let lit = Toggles {
        lighting: true,
        ..flat
    };
    let ground = |img: &[[u8; 3]]| -> Vec<[u8; 3]> {
        (80..108).flat_map(|y| row(img, y).to_vec()).collect()
    };
    let distinct = |px: &[[u8; 3]]| {
        let mut v = px.to_vec();
        v.sort();
        v.dedup();
        v.len()
    };
    let unlit = ground(&draw(&gpu, &t, true, flat));
    assert!(
        distinct(&unlit) <= 2,
        "one colour without lighting: {}",
        distinct(&unlit)
    );
    assert!(
        distinct(&ground(&draw(&gpu, &t, true, lit))) > 20,
        "lighting shades"
    );
    let dark = |px: &[[u8; 3]]| px.iter().filter(|p| p.iter().all(|&c| c < 40)).count();
    let wire = ground(&draw(
        &gpu,
        &t,
        true,
        Toggles {
            wireframe: true,
            ..flat
        },
    ));
    assert!(
        dark(&wire) > dark(&unlit) + 100,
        "wireframe lines: {} dark pixels",
        dark(&wire)
    );
}

#[test]
fn a_fixed_scene_matches_its_reference_image() {
    let gpu = gpu();
    let t = load("synth-257");
    let img = draw(&gpu, &t, false, Toggles::default());
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/reference/synth-257.png");
    let rgba: Vec<u8> = img.iter().flat_map(|p| [p[0], p[1], p[2], 255]).collect();
    if std::env::var_os("UPDATE_EXPECT").is_some() {
        std::fs::create_dir_all(path.parent().expect("a directory")).expect("create");
        render::write_png(&path, SIZE, &rgba).expect("writes");
    }
    let file = std::fs::File::open(&path)
        .unwrap_or_else(|e| panic!("{}: {e} (UPDATE_EXPECT=1 makes it)", path.display()));
    let mut dec = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .expect("a PNG");
    let mut want = vec![0; dec.output_buffer_size().expect("sized")];
    dec.next_frame(&mut want).expect("pixels");
    assert_eq!(want.len(), rgba.len());
    let diff = want
        .iter()
        .zip(&rgba)
        .map(|(&a, &b)| f64::from(a.abs_diff(b)))
        .sum::<f64>()
        / rgba.len() as f64;
    // Adapters round differently: a small mean difference is allowed.
    assert!(
        diff < 2.0,
        "mean difference {diff} per channel from the reference"
    );
}

/// Draws `mesh` from `view` with `markers`.
fn draw_view(
    gpu: &Gpu,
    t: &Terrain,
    mesh: &roam_protocol::Mesh,
    view: &View,
    markers: &[render::Marker],
    toggles: Toggles,
) -> Vec<[u8; 3]> {
    let mut r = renderer(gpu, t, false, wgpu::TextureFormat::Rgba8UnormSrgb);
    r.set_mesh(gpu, mesh);
    r.set_markers(markers);
    let rgba = render::render_offscreen(gpu, &mut r, SIZE, view, toggles).expect("renders");
    rgba.chunks(4).map(|p| [p[0], p[1], p[2]]).collect()
}

#[test]
fn water_covers_what_lies_below_its_level_and_can_be_switched_off() {
    let gpu = gpu();
    let t = load("synth-257");
    let water = t.map.water_level.expect("synth-257 has water") as f32;
    let (_, mesh) = view_and_mesh(&t);
    let size = t.world_size() as f32;
    // High over the middle, looking well down: land and lake both in view.
    let view = View {
        eye: [size * 0.5, water + size * 0.4, size * 0.2],
        yaw_deg: 0.0,
        pitch_deg: -40.0,
        fov_y_deg: 60.0,
        time_s: 0.0,
    };
    // Without the test's thick fog, which would hide it.
    let clear = Toggles {
        fog: false,
        ..Toggles::default()
    };
    let on = draw_view(&gpu, &t, &mesh, &view, &[], clear);
    let off = draw_view(
        &gpu,
        &t,
        &mesh,
        &view,
        &[],
        Toggles {
            water: false,
            ..clear
        },
    );
    if let Some(dir) = std::env::var_os("ROAM_DUMP") {
        let png = |img: &[[u8; 3]], name: &str| {
            let rgba: Vec<u8> = img.iter().flat_map(|p| [p[0], p[1], p[2], 255]).collect();
            render::write_png(&std::path::Path::new(&dir).join(name), SIZE, &rgba).expect("dump");
        };
        png(&on, "water-on.png");
        png(&off, "water-off.png");
    }
    let changed = on
        .iter()
        .zip(&off)
        .filter(|(a, b)| dist(**a, **b) > 6.0)
        .count();
    let total = on.len();
    assert!(
        changed > total / 40 && changed < total / 2,
        "water changes part of the picture, not all: {changed} of {total} pixels"
    );
    // The same time draws the same waves.
    assert_eq!(on, draw_view(&gpu, &t, &mesh, &view, &[], clear));
}

#[test]
fn other_vehicles_are_drawn_as_markers() {
    let gpu = gpu();
    let t = load("synth-257");
    let (view, mesh) = view_and_mesh(&t);
    // A red vehicle 40 m straight ahead of the camera (which looks east, level).
    let red = render::Marker {
        pos: [view.eye[0] + 40.0, view.eye[1] - 1.0, view.eye[2]],
        heading_deg: 90.0,
        color: [255, 0, 0],
    };
    let flat = Toggles {
        lighting: false,
        fog: false,
        ..Toggles::default()
    };
    let with = draw_view(&gpu, &t, &mesh, &view, &[red], flat);
    let reddish = |img: &[[u8; 3]]| {
        img.iter()
            .filter(|p| p[0] > 200 && p[1] < 60 && p[2] < 60)
            .count()
    };
    assert!(reddish(&with) > 20, "{} red pixels", reddish(&with));
    let without = draw_view(
        &gpu,
        &t,
        &mesh,
        &view,
        &[red],
        Toggles {
            vehicles: false,
            ..flat
        },
    );
    assert_eq!(reddish(&without), 0);
}

#[test]
fn a_target_that_does_not_encode_srgb_gets_the_same_picture() {
    let gpu = gpu();
    let t = load("synth-257");
    let (view, mesh) = view_and_mesh(&t);
    let draw_as = |format| {
        let mut r = renderer(&gpu, &t, false, format);
        r.set_mesh(&gpu, &mesh);
        render::render_offscreen(&gpu, &mut r, SIZE, &view, Toggles::default()).expect("renders")
    };
    let srgb = draw_as(wgpu::TextureFormat::Rgba8UnormSrgb);
    let plain = draw_as(wgpu::TextureFormat::Rgba8Unorm);
    let diff = srgb
        .iter()
        .zip(&plain)
        .map(|(&a, &b)| f64::from(a.abs_diff(b)))
        .sum::<f64>()
        / srgb.len() as f64;
    assert!(diff < 1.5, "mean difference {diff} per channel");
}

/// A flat map of 256 cells seen from straight above cell (32, 32), 40 cells up: about two
/// pixels a cell, so level 0 is the one the screen asks for. Colour: 256 cells in tiles of
/// 32 and a window of 2 (layers of 64²): levels of 8, 4, 2 and 1 tiles a side; each level
/// gets flat tiles of its own colour, where `tiles` says.
fn draw_clipmap(gpu: &Gpu, tiles: &[(u8, u32, u32, [u8; 3])]) -> Vec<[u8; 3]> {
    let color = ColorLayout::new(256, 32, 2).expect("a valid layout");
    assert_eq!(color.levels, 4);
    let scene = Scene {
        levels: 8,
        h_scale: 1.0,
        v_scale: 1.0,
        sun_dir: [0.0, 1.0, 0.0],
        sun_color: [255; 3],
        fog_density: 0.0,
        fog_color: [0; 3],
        water_level: None,
        color,
    };
    let mut cache = ColorCache::new(color, 8, 2, roam_client::color_cache::Keep::Texels)
        .expect("the layout fits the grid");
    for &(level, x, z, rgb) in tiles {
        let side = color.tile_side(level) as usize;
        let texels: Vec<u8> = std::iter::repeat_n(rgb, side * side).flatten().collect();
        cache.put_tile(level, x, z, &texels).expect("in the window");
    }
    let mut r = Renderer::new(gpu, wgpu::TextureFormat::Rgba8UnormSrgb, scene);
    r.update_colors(gpu, &cache.drain(usize::MAX));
    let flat = roam_protocol::Mesh {
        vertices: vec![[0, 0], [256, 0], [0, 256], [256, 256]],
        heights: vec![0; 4],
        indices: vec![0, 2, 1, 1, 2, 3],
    };
    r.set_mesh(gpu, &flat);
    let view = View {
        eye: [32.0, 40.0, 32.0],
        yaw_deg: 0.0,
        pitch_deg: -89.9,
        fov_y_deg: 60.0,
        time_s: 0.0,
    };
    let off = Toggles {
        fog: false,
        lighting: false,
        wireframe: false,
        water: false,
        vehicles: false,
        detail: false,
        normals: false,
    };
    let rgba = render::render_offscreen(gpu, &mut r, SIZE, &view, off).expect("renders");
    rgba.chunks(4).map(|p| [p[0], p[1], p[2]]).collect()
}

#[test]
fn the_finest_resident_colour_level_is_drawn_where_it_is_resident() {
    const RED: [u8; 3] = [255, 0, 0];
    const GREEN: [u8; 3] = [0, 255, 0];
    const BLUE: [u8; 3] = [0, 0, 255];
    let gpu = gpu();
    let is = |img: &[[u8; 3]], c: [u8; 3]| -> Vec<bool> {
        img.iter().map(|&p| dist(p, c) < 30.0).collect()
    };
    let count = |v: &[bool]| v.iter().filter(|&&b| b).count();
    // Level 0's tile (0, 0) covers cells 0 .. 32; the coarsest level the whole map.
    let fine = draw_clipmap(&gpu, &[(3, 0, 0, BLUE), (0, 0, 0, RED)]);
    let (red, blue) = (is(&fine, RED), is(&fine, BLUE));
    let total = fine.len();
    assert!(count(&red) > total / 10, "{} red of {total}", count(&red));
    assert!(count(&blue) > total / 5, "{} blue of {total}", count(&blue));
    // Level 1's tile (0, 0) instead covers cells 0 .. 64: green wherever red was, and more.
    let mid = draw_clipmap(&gpu, &[(3, 0, 0, BLUE), (1, 0, 0, GREEN)]);
    let green = is(&mid, GREEN);
    assert!(red.iter().zip(&green).all(|(&r, &g)| !r || g));
    assert!(count(&green) > count(&red) + total / 10);
    assert_eq!(count(&is(&mid, RED)), 0);
    // Both: red where level 0 is resident, green around it, blue beyond.
    let both = draw_clipmap(&gpu, &[(3, 0, 0, BLUE), (1, 0, 0, GREEN), (0, 0, 0, RED)]);
    assert_eq!(is(&both, RED), red);
    assert!(count(&is(&both, GREEN)) + count(&red) >= count(&green) - total / 100);
    // Only the coarsest level: blue wherever the ground is.
    let coarse = draw_clipmap(&gpu, &[(3, 0, 0, BLUE)]);
    let ground = |img: &[[u8; 3]]| img.iter().filter(|p| **p != [0, 0, 0]).count();
    assert!(count(&is(&coarse, BLUE)) >= ground(&fine) - total / 100);
}
