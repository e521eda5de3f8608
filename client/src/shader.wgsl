// Terrain and sky. Lighting: the map's sun (direction, colour) over an ambient term;
// fog: exp(-density * distance) towards the fog colour, which the sky fades into at the
// horizon; wireframe: edges found from barycentrics, so it works on every adapter.

struct Uniforms {
    view_proj: mat4x4<f32>,
    inv_view_proj: mat4x4<f32>,
    eye: vec4<f32>,
    sun_dir: vec4<f32>,
    sun_color: vec4<f32>,
    fog_color: vec4<f32>,
    // x: fog density, y: fog on, z: lighting on, w: wireframe on
    params: vec4<f32>,
};

@group(0) @binding(0) var<uniform> u: Uniforms;
@group(0) @binding(1) var colors: texture_2d<f32>;
@group(0) @binding(2) var colors_sampler: sampler;

struct TerrainOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) uv: vec2<f32>,
    @location(3) bary: vec3<f32>,
};

@vertex
fn terrain_vs(
    @location(0) pos: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) uv: vec2<f32>,
    @location(3) bary: vec3<f32>,
) -> TerrainOut {
    var out: TerrainOut;
    out.clip = u.view_proj * vec4<f32>(pos, 1.0);
    out.world = pos;
    out.normal = normal;
    out.uv = uv;
    out.bary = bary;
    return out;
}

fn fogged(c: vec3<f32>, dist: f32) -> vec3<f32> {
    if (u.params.y < 0.5) {
        return c;
    }
    let t = exp(-u.params.x * dist);
    return mix(u.fog_color.rgb, c, t);
}

@fragment
fn terrain_fs(in: TerrainOut) -> @location(0) vec4<f32> {
    let base = textureSample(colors, colors_sampler, in.uv).rgb;
    var c = base;
    if (u.params.z > 0.5) {
        let n = normalize(in.normal);
        let diffuse = max(dot(n, normalize(u.sun_dir.xyz)), 0.0);
        c = base * (vec3<f32>(0.35) + 0.75 * diffuse * u.sun_color.rgb);
    }
    if (u.params.w > 0.5) {
        let w = fwidth(in.bary);
        let e = smoothstep(vec3<f32>(0.0), w * 1.5, in.bary);
        let edge = min(min(e.x, e.y), e.z);
        c = mix(vec3<f32>(0.02, 0.02, 0.02), c, edge);
    }
    c = fogged(c, length(in.world - u.eye.xyz));
    return vec4<f32>(c, 1.0);
}

struct SkyOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) ndc: vec2<f32>,
};

@vertex
fn sky_vs(@builtin(vertex_index) i: u32) -> SkyOut {
    // One triangle covering the screen.
    let p = vec2<f32>(f32((i << 1u) & 2u) * 2.0 - 1.0, f32(i & 2u) * 2.0 - 1.0);
    var out: SkyOut;
    out.clip = vec4<f32>(p, 0.0, 1.0);
    out.ndc = p;
    return out;
}

@fragment
fn sky_fs(in: SkyOut) -> @location(0) vec4<f32> {
    let far = u.inv_view_proj * vec4<f32>(in.ndc, 1.0, 1.0);
    let dir = normalize(far.xyz / far.w - u.eye.xyz);
    let zenith = vec3<f32>(0.22, 0.42, 0.78);
    let horizon = u.fog_color.rgb;
    let up = clamp(dir.y, 0.0, 1.0);
    let sky = mix(horizon, zenith, smoothstep(0.0, 0.45, up));
    // The sun's disc.
    let sun = pow(max(dot(dir, normalize(u.sun_dir.xyz)), 0.0), 800.0);
    return vec4<f32>(sky + sun * u.sun_color.rgb, 1.0);
}
