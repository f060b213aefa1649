// The f16 kernels' first line (`linear_f16.wgsl`, `linear_coop.wgsl`): WGSL wants every `enable`
// before any declaration, and the engine prepends the shared helpers, so it comes first.
enable f16;
