//! The light per pixel, on a software adapter (lavapipe where there is no GPU): with the
//! terrain's normal tiles loaded, the light on a far slope does not change when the cut
//! drawn over it does (a coarse and a fine tessellation of the same heights, the same
//! camera), where with the vertex normals alone it does; and a tile's normals fade in
//! over the vertex normal, and a finer level's over a coarser one's, never popping.
//! Fog, water, detail and colour are neutral (uniform grey ground, no fog).
//!
//! Measured (lavapipe, 192 × 108, smooth hills, a cut of 2,000 triangles against one of
//! 60,000, the farthest third of the slopes' pixels): the light moves 1.00 (mean absolute
//! luminance, of 255) with normal tiles, 7.36 with vertex normals alone; what is left
//! with tiles is the ground itself moving (a coarse cut's surface is lower or higher, so
//! a pixel sees another point of the slope).

use std::sync::Arc;

use roam_client::color_cache::ColorCache;
use roam_client::render::{self, Gpu, Renderer, Scene, Toggles, View};
use roam_protocol::messages::ServerMessage;
use roam_protocol::tiles::ColorLayout;
use roam_server::terrain::normal_pyramid::NormalPyramid;
use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::camera::Camera;
use roam_server::tessellate::{Limits, Mesh, Scales, Tessellator};
use roam_server::{ColorMap, Heightfield, MapParams, Terrain};

const SIZE: (u32, u32) = (192, 108);
/// Tiles of 32 on the 256-cell map: levels of 8, 4, 2 and 1 tiles, all held whole.
const TILE: u32 = 32;
/// The sky's colour at the horizon (fog off): pure blue, never taken for grey ground.
const HORIZON: [u8; 3] = [0, 0, 255];

/// Smooth hills, 257² samples (256 cells), 30 m apart, up to 900 m high: long lit and
/// shaded slopes, no per-sample noise (the light may only move where the ground does).
fn terrain() -> Arc<Terrain> {
    let side = 257u32;
    let heights = (0..side * side)
        .map(|i| {
            let (x, z) = (f64::from(i % side), f64::from(i / side));
            let h = 20_000.0
                + 6_000.0 * (x / 20.0).sin() * (z / 26.0).cos()
                + 3_000.0 * ((x + 2.0 * z) / 14.0).sin();
            h as u16
        })
        .collect();
    let mut map = MapParams::default_for_side(side);
    map.h_scale = 30.0;
    map.v_scale = 0.1;
    let cells = side - 1;
    let grey = vec![[120; 3]; (cells * cells) as usize];
    Arc::new(Terrain {
        map,
        heights: Heightfield::new(side, heights).expect("a 2^N + 1 grid"),
        color: Some(ColorMap::new(cells, grey).expect("cells² texels")),
    })
}

/// The bundled rough terrain (`data/synth-257`): per-sample detail, so level 0's normals
/// differ from the coarser levels' averages.
fn rough() -> Arc<Terrain> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/synth-257");
    Arc::new(roam_server::terrain::dataset::load(&dir, &mut |_, _| {}).expect("bundled"))
}

fn layout(t: &Terrain) -> ColorLayout {
    ColorLayout::new(t.heights.size(), TILE, 8).expect("a valid layout")
}

fn scene(t: &Terrain) -> Scene {
    let m = &t.map;
    Scene {
        levels: t.heights.levels(),
        h_scale: m.h_scale,
        v_scale: m.v_scale,
        // Low, from the south-west: slopes facing it and away differ.
        sun_dir: [-0.5, 0.45, 0.74],
        sun_color: [255; 3],
        fog_density: 0.0,
        fog_color: HORIZON,
        water_level: None,
        color: layout(t),
    }
}

const LIT: Toggles = Toggles {
    fog: false,
    lighting: true,
    wireframe: false,
    water: false,
    vehicles: false,
    detail: false,
    normals: true,
};

/// The camera high over the map's west edge, looking east and down across it.
fn camera(t: &Terrain) -> (Camera, View) {
    let size = t.world_size();
    let ground = t.world_height(0, t.heights.size() / 2);
    let eye = [size * 0.02, ground + size * 0.15, size * 0.5];
    let (yaw, pitch) = (90.0, -25.0);
    let cam = Camera {
        eye,
        yaw_deg: yaw,
        pitch_deg: pitch,
        fov_y_deg: 60.0,
        width: SIZE.0,
        height: SIZE.1,
    };
    let view = View {
        eye: eye.map(|v| v as f32),
        yaw_deg: yaw as f32,
        pitch_deg: pitch as f32,
        fov_y_deg: 60.0,
        time_s: 0.0,
    };
    (cam, view)
}

/// A cut of `budget` triangles for the camera: the mesh a viewer would draw.
fn cut(t: &Terrain, budget: u32) -> roam_protocol::Mesh {
    let (cam, _) = camera(t);
    let vt = VarianceTree::build(&t.heights, 1, &mut |_, _| {});
    let mut tess = Tessellator::new(t.heights.side());
    let mut mesh = Mesh::default();
    let scales = Scales {
        h: t.map.h_scale,
        v: t.map.v_scale,
    };
    let limits = Limits {
        budget,
        threshold_px: 0.0,
        fog_density: 0.0,
        guard_deg: 0.0,
    };
    tess.tessellate(&t.heights, &vt, scales, &cam, limits, &mut mesh);
    let heights = mesh
        .vertices
        .iter()
        .map(|v| t.heights.get(u32::from(v[0]), u32::from(v[1])))
        .collect();
    roam_protocol::Mesh {
        vertices: mesh.vertices,
        heights,
        indices: mesh.indices,
    }
}

/// The terrain's normal tiles as the server codes them.
fn pyramid(t: &Terrain) -> NormalPyramid {
    let scales = (t.map.h_scale, t.map.v_scale);
    NormalPyramid::build(&t.heights, scales, TILE, 2, &mut |_, _| {}).expect("a valid grid")
}

/// A cache with the uniform grey colour and the normal tiles of `levels` (through the
/// protocol's message, as a viewer takes them).
fn cache(t: &Terrain, p: &NormalPyramid, levels: std::ops::Range<u8>) -> ColorCache {
    let l = layout(t);
    let grey = vec![120u8; (l.cells * l.cells * 3) as usize];
    let mut c = ColorCache::whole(l, &grey).expect("the layout's map");
    for level in levels {
        add_normals(&mut c, p, level);
    }
    c
}

fn add_normals(c: &mut ColorCache, p: &NormalPyramid, level: u8) {
    let n = c.layout().tiles(level);
    for z in 0..n {
        for x in 0..n {
            let data = p.tile(level, x, z).expect("in the pyramid").to_vec();
            let msg = ServerMessage::NormalTile { level, x, z, data };
            assert_eq!(c.apply(&msg), Ok(true));
        }
    }
}

fn gpu() -> Gpu {
    Gpu::headless().unwrap_or_else(|e| panic!("{e:#}"))
}

fn renderer(
    gpu: &Gpu,
    t: &Terrain,
    cache: &mut ColorCache,
    mesh: &roam_protocol::Mesh,
) -> Renderer {
    let mut r = Renderer::new(gpu, wgpu::TextureFormat::Rgba8UnormSrgb, scene(t));
    r.update_colors(gpu, &cache.drain(usize::MAX));
    r.set_mesh(gpu, mesh);
    r
}

fn draw(gpu: &Gpu, r: &mut Renderer, view: &View, toggles: Toggles) -> Vec<[u8; 3]> {
    let rgba = render::render_offscreen(gpu, r, SIZE, view, toggles).expect("renders");
    rgba.chunks(4).map(|p| [p[0], p[1], p[2]]).collect()
}

/// Whether a pixel is ground (grey, whatever its light) rather than sky (blue).
fn ground(p: [u8; 3]) -> bool {
    p[0].abs_diff(p[1]) <= 3 && p[1].abs_diff(p[2]) <= 3
}

fn luminance(p: [u8; 3]) -> f64 {
    0.2126 * f64::from(p[0]) + 0.7152 * f64::from(p[1]) + 0.0722 * f64::from(p[2])
}

/// The mean absolute luminance difference over `pixels`.
fn mean_diff(a: &[[u8; 3]], b: &[[u8; 3]], pixels: &[usize]) -> f64 {
    pixels
        .iter()
        .map(|&i| (luminance(a[i]) - luminance(b[i])).abs())
        .sum::<f64>()
        / pixels.len().max(1) as f64
}

fn dump(name: &str, img: &[[u8; 3]]) {
    if let Some(dir) = std::env::var_os("ROAM_DUMP") {
        let rgba: Vec<u8> = img.iter().flat_map(|p| [p[0], p[1], p[2], 255]).collect();
        render::write_png(&std::path::Path::new(&dir).join(name), SIZE, &rgba).expect("dump");
    }
}

#[test]
fn the_light_on_a_far_slope_does_not_change_with_the_cut() {
    let gpu = gpu();
    let t = terrain();
    let p = pyramid(&t);
    let (_, view) = camera(&t);
    let (coarse, fine) = (cut(&t, 2_000), cut(&t, 60_000));
    assert!(
        fine.indices.len() > 20 * coarse.indices.len(),
        "two different cuts"
    );
    let levels = layout(&t).levels;
    let draw_with = |mesh: &roam_protocol::Mesh, normals: bool| {
        let mut c = cache(&t, &p, if normals { 0..levels } else { 0..0 });
        let mut r = renderer(&gpu, &t, &mut c, mesh);
        draw(&gpu, &mut r, &view, LIT)
    };
    let (tiles_coarse, tiles_fine) = (draw_with(&coarse, true), draw_with(&fine, true));
    let (vertex_coarse, vertex_fine) = (draw_with(&coarse, false), draw_with(&fine, false));
    let all = [&tiles_coarse, &tiles_fine, &vertex_coarse, &vertex_fine];
    for (name, img) in ["tiles-coarse", "tiles-fine", "vertex-coarse", "vertex-fine"]
        .iter()
        .zip(all)
    {
        dump(&format!("{name}.png"), img);
    }
    // The slopes' pixels: ground in all four pictures, and so are their four neighbours
    // (a silhouette moves with the cut, the light on a slope must not); the far ones are
    // the top third of them (the cut is coarsest far away).
    let w = SIZE.0 as usize;
    let inside = |i: usize| {
        all.iter().all(|img| {
            [i, i.saturating_sub(1), i + 1, i.saturating_sub(w), i + w]
                .iter()
                .all(|&j| j < img.len() && ground(img[j]))
        })
    };
    let slopes: Vec<usize> = (0..tiles_fine.len()).filter(|&i| inside(i)).collect();
    let far = &slopes[..slopes.len() / 3];
    assert!(far.len() > 3_000, "{} far slope pixels", far.len());
    let with_tiles = mean_diff(&tiles_coarse, &tiles_fine, far);
    let with_vertices = mean_diff(&vertex_coarse, &vertex_fine, far);
    eprintln!(
        "far slopes, {} pixels: the light moved {with_tiles:.2} with normal tiles, \
         {with_vertices:.2} with vertex normals (mean |Δ luminance|, of 255)",
        far.len()
    );
    // The light is lit: it varies over the slopes.
    let spread = {
        let l: Vec<f64> = far.iter().map(|&i| luminance(tiles_fine[i])).collect();
        let mean = l.iter().sum::<f64>() / l.len() as f64;
        (l.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / l.len() as f64).sqrt()
    };
    assert!(spread > 10.0, "lighting shades the slopes: σ {spread:.1}");
    assert!(
        with_tiles < 1.5,
        "normal tiles: the light moved {with_tiles:.2}"
    );
    assert!(
        with_vertices > 5.0 && with_vertices > 4.0 * with_tiles,
        "vertex normals (the control): the light moved only {with_vertices:.2}"
    );
}

#[test]
fn normals_fade_in_over_the_vertex_normal_and_finer_over_coarser() {
    let gpu = gpu();
    let t = rough();
    let p = pyramid(&t);
    let (_, view) = camera(&t);
    let mesh = cut(&t, 2_000);
    let levels = layout(&t).levels;
    let at = |time_s: f32| View { time_s, ..view };
    let image = |range: std::ops::Range<u8>| {
        let mut c = cache(&t, &p, range);
        let mut r = renderer(&gpu, &t, &mut c, &mesh);
        draw(&gpu, &mut r, &at(10.0), LIT)
    };
    let (none, coarse_only, all) = (image(0..0), image(1..levels), image(0..levels));
    let pixels: Vec<usize> = (0..none.len()).filter(|&i| ground(none[i])).collect();
    let d = |a: &[[u8; 3]], b: &[[u8; 3]]| mean_diff(a, b, &pixels);
    assert!(d(&none, &all) > 2.0, "the tiles change the light");
    assert!(d(&coarse_only, &all) > 0.5, "level 0 changes the light");
    for (before, arriving, what) in [(0..0, 0..levels, "every level over the vertex normals")]
        .into_iter()
        .chain([(1..levels, 0..1, "level 0 over the coarser levels")])
    {
        let mut c = cache(&t, &p, before.clone());
        let mut r = renderer(&gpu, &t, &mut c, &mesh);
        draw(&gpu, &mut r, &at(10.0), LIT);
        for level in arriving {
            add_normals(&mut c, &p, level);
        }
        r.update_colors(&gpu, &c.drain(usize::MAX));
        let from = if before.is_empty() {
            &none
        } else {
            &coarse_only
        };
        let frames: Vec<Vec<[u8; 3]>> = [10.0, 10.25, 10.5, 11.0]
            .map(|s| draw(&gpu, &mut r, &at(s), LIT))
            .into();
        let step = d(from, &all);
        // At once: the picture before (within a byte's fade); half way: between; after
        // half a second: the picture with them.
        assert!(d(&frames[0], from) < 0.02 * step + 0.3, "{what}: popped in");
        let (to_from, to_all) = (d(&frames[1], from), d(&frames[1], &all));
        assert!(
            to_from > 0.25 * step && to_all > 0.25 * step,
            "{what}: half way is between ({to_from:.2}, {to_all:.2} of {step:.2})"
        );
        assert!(d(&frames[2], &all) < 0.3, "{what}: faded in");
        assert_eq!(frames[2], frames[3], "{what}: and stays");
    }
}
