// Tensor cores through naga's cooperative matrices (`linear_coop.wgsl`), enabled only on an
// adapter that offers `EXPERIMENTAL_COOPERATIVE_MATRIX` (the engine compiles the family there
// alone).
enable wgpu_cooperative_matrix;
