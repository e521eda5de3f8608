//! `roam-bindgen WASM OUT_DIR`: what `wasm-bindgen --target web --no-typescript --out-dir
//! OUT_DIR WASM` does (the same library, the same options, the same files), for
//! `scripts/build-web`, which builds this instead of installing wasm-bindgen's CLI.

use std::process::ExitCode;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [wasm, out] = args.as_slice() else {
        eprintln!("usage: roam-bindgen WASM OUT_DIR");
        return ExitCode::from(2);
    };
    // Every option the CLI sets, at the CLI's defaults (the library's own defaults differ:
    // it omits the default path of the wasm in `init`, which the page relies on).
    let mut b = wasm_bindgen_cli_support::Bindgen::new();
    let bound = b.input_path(wasm).web(true).map(|b| {
        b.debug(false)
            .demangle(true)
            .keep_lld_exports(false)
            .keep_debug(false)
            .split_debug_info(false)
            .remove_name_section(false)
            .remove_producers_section(false)
            .typescript(false)
            .omit_imports(false)
            .omit_default_module_path(false)
            .split_linked_modules(false)
            .js_string_builtins(false)
            .ts_typed_array_buffers(false)
            .reset_state_function(false)
            .force_enable_abort_handler(false)
            .generate(out)
    });
    match bound {
        Ok(Ok(())) => ExitCode::SUCCESS,
        Ok(Err(e)) | Err(e) => {
            eprintln!("error: binding {wasm} into {out}: {e:#}");
            ExitCode::FAILURE
        }
    }
}
