// Terrain, water, vehicle markers and sky. Lighting: the map's sun (direction, colour) over
// an ambient term; fog: exp(-density * distance) towards the fog colour, which the sky
// fades into at the horizon; wireframe: edges found from barycentrics (derived from the
// vertex index, the mesh being drawn unindexed), so it works on every adapter. Depth is
// reversed (1 near, 0 at infinity). Colour: a clipmap, a texture-array layer per level of
// the colour pyramid, addressed toroidally (see `color_at`). Light: the terrain's normals
// per pixel from a second clipmap of the same shape, each tile faded in over the vertex
// normal (see `normal_at`).

struct Uniforms {
    view_proj: mat4x4<f32>,
    inv_view_proj: mat4x4<f32>,
    eye: vec4<f32>,
    sun_dir: vec4<f32>,
    sun_color: vec4<f32>,
    fog_color: vec4<f32>,
    // x: fog density, y: fog on, z: lighting on, w: wireframe on
    params: vec4<f32>,
    // x: map size (world units), y: water level, z: time (s), w: detail texture on
    map: vec4<f32>,
    // x: the target is not sRGB: encode here; y: light per pixel from the normal tiles
    output: vec4<f32>,
};

// The colour to write: linear, or sRGB-encoded for a target that does not encode.
fn out(c: vec3<f32>) -> vec3<f32> {
    if (u.output.x < 0.5) {
        return c;
    }
    let lo = c * 12.92;
    let hi = 1.055 * pow(max(c, vec3<f32>(0.0)), vec3<f32>(1.0 / 2.4)) - 0.055;
    return select(hi, lo, c <= vec3<f32>(0.0031308));
}

@group(0) @binding(0) var<uniform> u: Uniforms;
@group(0) @binding(1) var colors: texture_2d_array<f32>;
@group(0) @binding(2) var colors_sampler: sampler;

struct ColorLevel {
    // x0, z0: the window's origin (tiles); z: the level's side (texels)
    origin: vec4<u32>,
    // Tiles drawn: bit (z mod W)·W + (x mod W), 32 to a word
    mask: array<vec4<u32>, 2>,
};

struct ColorLevels {
    // x: levels (0: no colour), y: W (tiles), z: T (texels), w: S (texels a layer)
    info: vec4<u32>,
    level: array<ColorLevel, 16>,
};

@group(0) @binding(3) var<uniform> cl: ColorLevels;

// Whether tile (tx, tz) of level l is in its window and drawn.
fn tile_drawn(l: u32, tx: u32, tz: u32) -> bool {
    let w = cl.info.y;
    let o = cl.level[l].origin;
    // Unsigned: a tile before the origin wraps to a large number.
    if (tx - o.x >= w || tz - o.y >= w) {
        return false;
    }
    let b = (tz % w) * w + (tx % w);
    let word = cl.level[l].mask[b / 128u][(b / 32u) % 4u];
    return ((word >> (b % 32u)) & 1u) == 1u;
}

// Whether the bilinear footprint at p (texels of level l, clamped inside it) is drawn:
// the tiles of its lowest and highest texels in both axes.
fn footprint_drawn(l: u32, p: vec2<f32>) -> bool {
    let last = cl.level[l].origin.z - 1u;
    let lo = vec2<u32>(max(p - 0.5, vec2<f32>(0.0)));
    let hi = min(vec2<u32>(p + 0.5), vec2<u32>(last));
    let t = cl.info.z;
    let a = lo / t;
    let b = hi / t;
    return tile_drawn(l, a.x, a.y) && tile_drawn(l, b.x, a.y) && tile_drawn(l, a.x, b.y)
        && tile_drawn(l, b.x, b.y);
}

// The screen-space level of detail at level-0 cell coordinate `cell`: log2 of level-0
// texels per pixel (derivatives: call in uniform control flow).
fn lod_at(cell: vec2<f32>) -> f32 {
    let d = max(length(dpdx(cell)), length(dpdy(cell)));
    return max(log2(max(d, 1e-6)), 0.0);
}

// The ground's colour at level-0 cell coordinate `cell` from level `first` or, where its
// footprint is not drawn, the finest coarser level whose footprint is; grey before any.
fn color_from(cell: vec2<f32>, first: u32) -> vec3<f32> {
    let levels = cl.info.x;
    var l = first;
    loop {
        let side = f32(cl.level[l].origin.z);
        let p = clamp(cell / f32(1u << l), vec2<f32>(0.5), vec2<f32>(side - 0.5));
        if (footprint_drawn(l, p)) {
            let uv = p / f32(cl.info.w);
            return textureSampleLevel(colors, colors_sampler, uv, i32(l), 0.0).rgb;
        }
        if (l + 1u >= levels) {
            break;
        }
        l += 1u;
    }
    return vec3<f32>(0.5);
}

// The ground's colour at level-0 cell coordinate `cell`, trilinear: the levels either side
// of the screen-space level of detail `lod`, the finer weighted by one minus its fraction
// (as `normal_at`). Taking the finer level alone (the first version) switched a pixel
// between two levels wherever `lod` crossed a whole number, and a surface moving by a
// fraction of a pixel (a geomorph, the vehicle's motion) moves where it crosses: the
// colour flickered along those lines.
fn color_at(cell: vec2<f32>, lod: f32) -> vec3<f32> {
    let levels = cl.info.x;
    if (levels == 0u) {
        return vec3<f32>(0.5);
    }
    let l = min(u32(lod), levels - 1u);
    let fine = color_from(cell, l);
    if (l + 1u >= levels) {
        return fine;
    }
    return mix(fine, color_from(cell, l + 1u), fract(lod));
}

// Normals: the fade of each tile (a byte per level and window slot, 0: none), and the
// normal clipmap (each texel's hemi-octahedral code, `roam_protocol::normals`).
struct NormalFades {
    // Byte l·256 + slot, four to a word.
    fade: array<vec4<u32>, 256>,
};

@group(0) @binding(4) var normal_maps: texture_2d_array<f32>;
@group(0) @binding(5) var<uniform> nf: NormalFades;

// The fade of tile (tx, tz)'s normals at level l (0 outside the window or without them).
fn tile_fade(l: u32, tx: u32, tz: u32) -> f32 {
    let w = cl.info.y;
    let o = cl.level[l].origin;
    if (tx - o.x >= w || tz - o.y >= w) {
        return 0.0;
    }
    let i = l * 256u + (tz % w) * w + (tx % w);
    let word = nf.fade[i / 16u][(i / 4u) % 4u];
    return f32((word >> ((i % 4u) * 8u)) & 255u) / 255.0;
}

// The least fade over the bilinear footprint at p (texels of level l), as for colour.
fn footprint_fade(l: u32, p: vec2<f32>) -> f32 {
    let last = cl.level[l].origin.z - 1u;
    let lo = vec2<u32>(max(p - 0.5, vec2<f32>(0.0)));
    let hi = min(vec2<u32>(p + 0.5), vec2<u32>(last));
    let t = cl.info.z;
    let a = lo / t;
    let b = hi / t;
    return min(min(tile_fade(l, a.x, a.y), tile_fade(l, b.x, a.y)),
        min(tile_fade(l, a.x, b.y), tile_fade(l, b.x, b.y)));
}

// A normal from its code's two bytes (as unorm, bilinearly filtered).
fn decode_normal(e: vec2<f32>) -> vec3<f32> {
    let ab = clamp((e * 255.0 - 128.0) / 127.0, vec2<f32>(-1.0), vec2<f32>(1.0));
    let p = vec2<f32>(ab.x + ab.y, ab.x - ab.y) * 0.5;
    return normalize(vec3<f32>(p.x, max(1.0 - abs(p.x) - abs(p.y), 0.0), p.y));
}

// The ground's normal at level-0 cell coordinate `cell`: from the levels either side of
// `lod` (trilinear: the finer one weighted by one minus `lod`'s fraction, so the light
// moves smoothly as the level of detail does, which the cut drawn changes too), a level
// without normals under its footprint giving way to the next coarser, composited over
// the coarser levels' and finally the vertex normal `vn` by each one's fade, front to
// back: tiles fully faded in hide everything behind them (two samples, the usual case).
fn normal_at(cell: vec2<f32>, lod: f32, vn: vec3<f32>) -> vec3<f32> {
    let levels = cl.info.x;
    if (levels == 0u || u.output.y < 0.5) {
        return vn;
    }
    var acc = vec3<f32>(0.0);
    var left = 1.0;
    var l = min(u32(lod), levels - 1u);
    // The finer level's share; the coarsest level takes all.
    var share = select(1.0 - fract(lod), 1.0, l + 1u >= levels);
    loop {
        let side = f32(cl.level[l].origin.z);
        let p = clamp(cell / f32(1u << l), vec2<f32>(0.5), vec2<f32>(side - 0.5));
        let f = footprint_fade(l, p) * share;
        share = 1.0;
        if (f > 0.0) {
            let uv = p / f32(cl.info.w);
            let e = textureSampleLevel(normal_maps, colors_sampler, uv, i32(l), 0.0).rg;
            acc += left * f * decode_normal(e);
            left *= 1.0 - f;
            if (left <= 0.0) {
                break;
            }
        }
        if (l + 1u >= levels) {
            break;
        }
        l += 1u;
    }
    return normalize(acc + left * vn);
}

fn fogged(c: vec3<f32>, dist: f32) -> vec3<f32> {
    if (u.params.y < 0.5) {
        return c;
    }
    let t = exp(-u.params.x * dist);
    return mix(u.fog_color.rgb, c, t);
}

fn lit(base: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    if (u.params.z < 0.5) {
        return base;
    }
    let diffuse = max(dot(n, normalize(u.sun_dir.xyz)), 0.0);
    return base * (vec3<f32>(0.35) + 0.75 * diffuse * u.sun_color.rgb);
}

// The sky seen along `dir`: the fog colour at the horizon, blue above, and the sun.
fn sky_color(dir: vec3<f32>) -> vec3<f32> {
    let zenith = vec3<f32>(0.22, 0.42, 0.78);
    let up = clamp(dir.y, 0.0, 1.0);
    let sky = mix(u.fog_color.rgb, zenith, smoothstep(0.0, 0.45, up));
    let sun = pow(max(dot(dir, normalize(u.sun_dir.xyz)), 0.0), 800.0);
    return sky + sun * u.sun_color.rgb;
}

// A hash of a lattice point, in [0, 1).
fn hash2(p: vec2<f32>) -> f32 {
    var q = fract(p * vec2<f32>(0.1031, 0.1030));
    q += dot(q, q.yx + 33.33);
    return fract((q.x + q.y) * q.x);
}

// Smooth value noise, in [0, 1].
fn value_noise(p: vec2<f32>) -> f32 {
    let i = floor(p);
    let f = fract(p);
    let s = f * f * (3.0 - 2.0 * f);
    let a = mix(hash2(i), hash2(i + vec2<f32>(1.0, 0.0)), s.x);
    let b = mix(hash2(i + vec2<f32>(0.0, 1.0)), hash2(i + vec2<f32>(1.0, 1.0)), s.x);
    return mix(a, b, s.y);
}

// The detail texture: the colour map has one texel per grid cell (92 m on the bundled
// map), so near the camera the ground is modulated by noise at 2.3, 9 and 37 m. An octave
// fades out where it is smaller than a few pixels (no aliasing), and all of it with
// distance.
fn detail(xz: vec2<f32>, dist: f32) -> f32 {
    let footprint = max(length(fwidth(xz)), 1e-4);
    var sum = 0.0;
    var weight = 0.0;
    let scales = vec3<f32>(2.3, 9.1, 37.0);
    let amounts = vec3<f32>(0.35, 0.35, 0.3);
    for (var k = 0; k < 3; k++) {
        let fade = clamp(scales[k] / (3.0 * footprint) - 1.0, 0.0, 1.0);
        sum += amounts[k] * fade * (value_noise(xz / scales[k] + f32(k) * 17.0) - 0.5);
        weight += amounts[k];
    }
    let near = clamp(1.0 - dist / 3000.0, 0.0, 1.0);
    return 1.0 + 0.9 * near * sum / weight;
}

struct TerrainOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) bary: vec3<f32>,
};

@vertex
fn terrain_vs(
    @builtin(vertex_index) index: u32,
    @location(0) pos: vec3<f32>,
    @location(1) normal: vec4<f32>,
) -> TerrainOut {
    var out: TerrainOut;
    out.clip = u.view_proj * vec4<f32>(pos, 1.0);
    out.world = pos;
    out.normal = normal.xyz;
    let corner = index % 3u;
    out.bary = vec3<f32>(f32(corner == 0u), f32(corner == 1u), f32(corner == 2u));
    return out;
}

@fragment
fn terrain_fs(in: TerrainOut) -> @location(0) vec4<f32> {
    let cells = f32(cl.level[0].origin.z);
    let cell = in.world.xz / u.map.x * cells;
    let lod = lod_at(cell);
    var base = color_at(cell, lod);
    let dist = length(in.world - u.eye.xyz);
    if (u.map.w > 0.5) {
        base *= detail(in.world.xz, dist);
    }
    var c = lit(base, normal_at(cell, lod, normalize(in.normal)));
    if (u.params.w > 0.5) {
        let w = fwidth(in.bary);
        let e = smoothstep(vec3<f32>(0.0), w * 1.5, in.bary);
        let edge = min(min(e.x, e.y), e.z);
        c = mix(vec3<f32>(0.02, 0.02, 0.02), c, edge);
    }
    c = fogged(c, dist);
    return vec4<f32>(out(c), 1.0);
}

struct WaterOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
};

// Two triangles covering the map at the water level.
@vertex
fn water_vs(@builtin(vertex_index) i: u32) -> WaterOut {
    var corners = array<vec2<f32>, 6>(
        vec2<f32>(0.0, 0.0), vec2<f32>(0.0, 1.0), vec2<f32>(1.0, 0.0),
        vec2<f32>(1.0, 0.0), vec2<f32>(0.0, 1.0), vec2<f32>(1.0, 1.0),
    );
    let c = corners[i] * u.map.x;
    let p = vec3<f32>(c.x, u.map.y, c.y);
    var out: WaterOut;
    out.clip = u.view_proj * vec4<f32>(p, 1.0);
    out.world = p;
    return out;
}

// Water: ripples from a few moving waves bend the normal; the sky is reflected by Fresnel's
// law (Schlick), the sun glints, and what is left lets the lake bed's colour show through.
@fragment
fn water_fs(in: WaterOut) -> @location(0) vec4<f32> {
    let t = u.map.z;
    let p = in.world.xz;
    var slope = vec2<f32>(0.0);
    let waves = array<vec4<f32>, 4>(
        // direction (x, z), wavelength (m), speed (m/s)
        vec4<f32>(0.8, 0.6, 23.0, 2.1),
        vec4<f32>(-0.5, 0.86, 11.0, 1.4),
        vec4<f32>(0.96, -0.28, 5.3, 0.9),
        vec4<f32>(-0.2, -0.98, 2.7, 0.6),
    );
    // A pixel's footprint on the water: waves shorter than a few of them would alias into
    // noise, so they fade out as they shrink.
    let footprint = max(length(fwidth(p)), 1e-4);
    for (var k = 0; k < 4; k++) {
        let w = waves[k];
        let f = 6.2831853 / w.z;
        let fade = clamp(w.z / (4.0 * footprint) - 1.0, 0.0, 1.0);
        slope += w.xy * (0.045 * fade * cos(dot(w.xy, p) * f - t * w.w * f));
    }
    let dist = length(in.world - u.eye.xyz);
    let n = normalize(vec3<f32>(-slope.x, 1.0, -slope.y));
    let view = normalize(u.eye.xyz - in.world);
    let cos_v = max(dot(n, view), 0.0);
    let fresnel = 0.02 + 0.98 * pow(1.0 - cos_v, 5.0);
    let r = reflect(-view, n);
    let reflected = sky_color(vec3<f32>(r.x, abs(r.y), r.z));
    let deep = vec3<f32>(0.03, 0.11, 0.14);
    var c = mix(deep, reflected, fresnel);
    if (u.params.z > 0.5) {
        let h = normalize(normalize(u.sun_dir.xyz) + view);
        c += u.sun_color.rgb * pow(max(dot(n, h), 0.0), 400.0) * 2.0;
    }
    let alpha = mix(0.6, 1.0, fresnel);
    return vec4<f32>(out(fogged(c, dist)), alpha);
}

struct MarkerOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) color: vec3<f32>,
};

// A vehicle: the model turned to its heading, scaled, and placed.
@vertex
fn marker_vs(
    @location(0) pos: vec3<f32>,
    @location(1) normal: vec4<f32>,
    // x, y, z, heading (degrees)
    @location(2) place: vec4<f32>,
    // scale, then unused
    @location(3) scale: vec4<f32>,
    @location(4) color: vec4<f32>,
) -> MarkerOut {
    let h = radians(place.w);
    let s = sin(h);
    let c = cos(h);
    let turn = mat3x3<f32>(
        vec3<f32>(c, 0.0, -s),
        vec3<f32>(0.0, 1.0, 0.0),
        vec3<f32>(s, 0.0, c),
    );
    let world = place.xyz + turn * (pos * scale.x);
    var out: MarkerOut;
    out.clip = u.view_proj * vec4<f32>(world, 1.0);
    out.world = world;
    out.normal = turn * normal.xyz;
    out.color = color.rgb;
    return out;
}

@fragment
fn marker_fs(in: MarkerOut) -> @location(0) vec4<f32> {
    let c = lit(in.color, normalize(in.normal));
    // Markers are meant to be seen: fog them half as much as the terrain.
    return vec4<f32>(out(fogged(c, 0.5 * length(in.world - u.eye.xyz))), 1.0);
}

struct SkyOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) ndc: vec2<f32>,
};

@vertex
fn sky_vs(@builtin(vertex_index) i: u32) -> SkyOut {
    // One triangle covering the screen, at infinity.
    let p = vec2<f32>(f32((i << 1u) & 2u) * 2.0 - 1.0, f32(i & 2u) * 2.0 - 1.0);
    var out: SkyOut;
    out.clip = vec4<f32>(p, 0.0, 1.0);
    out.ndc = p;
    return out;
}

@fragment
fn sky_fs(in: SkyOut) -> @location(0) vec4<f32> {
    // Depth 0 is infinitely far: the inverse gives the ray's direction (w = 0), with no
    // eye subtracted, so no precision is lost 100 km from the origin.
    let dir = normalize((u.inv_view_proj * vec4<f32>(in.ndc, 0.0, 1.0)).xyz);
    return vec4<f32>(out(sky_color(dir)), 1.0);
}
