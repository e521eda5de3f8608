//! The shader on WebGL2, without a browser: the page falls back to WebGL2 (GLSL ES 3.00)
//! where there is no WebGPU, so every entry point must validate without the capabilities
//! WebGL2 lacks and translate to GLSL ES 3.00 for WebGL, with no storage buffers, and its
//! uniform blocks within WebGL2's 16 KiB (the normal fades' uniform is 4 KiB).

use naga::back::glsl;
use naga::valid::{Capabilities, ValidationFlags, Validator};

const SHADER: &str = include_str!("../../src/render/shader.wgsl");

#[test]
fn every_entry_point_translates_to_glsl_es_300_for_webgl() {
    let module = naga::front::wgsl::parse_str(SHADER).expect("the shader parses");
    let info = Validator::new(ValidationFlags::all(), Capabilities::empty())
        .validate(&module)
        .expect("the shader validates without extra capabilities");
    let options = glsl::Options {
        version: glsl::Version::Embedded {
            version: 300,
            is_webgl: true,
        },
        ..glsl::Options::default()
    };
    let limit = wgpu::Limits::downlevel_webgl2_defaults();
    let mut entries = 0;
    for entry in &module.entry_points {
        let pipeline = glsl::PipelineOptions {
            shader_stage: entry.stage,
            entry_point: entry.name.clone(),
            multiview: None,
        };
        let mut out = String::new();
        let mut writer = glsl::Writer::new(
            &mut out,
            &module,
            &info,
            &options,
            &pipeline,
            naga::proc::BoundsCheckPolicies::default(),
        )
        .unwrap_or_else(|e| panic!("{}: {e}", entry.name));
        writer
            .write()
            .unwrap_or_else(|e| panic!("{}: {e}", entry.name));
        assert!(out.starts_with("#version 300 es"), "{}", entry.name);
        assert!(!out.contains("buffer "), "{}: a storage buffer", entry.name);
        entries += 1;
    }
    assert_eq!(
        entries, 8,
        "four pipelines, a vertex and a fragment stage each"
    );
    // Every uniform block within WebGL2's limit.
    let mut layouter = naga::proc::Layouter::default();
    layouter
        .update(module.to_ctx())
        .expect("the shader's types lay out");
    for (_, var) in module.global_variables.iter() {
        if var.space == naga::AddressSpace::Uniform {
            let size = layouter[var.ty].size;
            assert!(
                size <= limit.max_uniform_buffer_binding_size as u32,
                "{:?}: {size} bytes",
                var.name
            );
        }
    }
}
