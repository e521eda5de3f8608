//! The viewer's integration tests: one test binary, each file a module (docs/testing.md).
//!
//! The modules named `needs_…` need something outside Rust (a GPU driver, a display, a NATS
//! server, a browser); the fast tier, `scripts/test-fast`, leaves them out by those names.
// A test binary has no users: its helpers' `pub` reach no one else (the lint is for
// libraries' interfaces), and tests print their figures for `--nocapture`.
#![allow(unreachable_pub, clippy::print_stdout)]

mod cli;
mod shader_webgl2;

/// Tests that open a real window: they need a display (Xvfb) and `xdotool`, and a Vulkan driver.
mod needs_display {
    mod window;
}

/// Tests that draw with wgpu: they need a Vulkan driver (without a GPU, lavapipe).
mod needs_gpu {
    mod render;
    mod render_normals;
}
