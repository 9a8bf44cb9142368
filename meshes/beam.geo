// Cantilever beam for demos/beam_swing.py and the benchmarks: a box [0, L] x [0, W] x [0, H].
// Physical groups: volume "beam" (cell tag 1), surfaces "clamp" (x = 0, facet tag 1) and
// "tip" (x = L, facet tag 2). Override the constants with -setnumber (diffsolids.mesh.from_geo's
// `numbers`), e.g. {"h": 0.02}.
SetFactory("OpenCASCADE");

DefineConstant[
  L = {1.0, Name "Parameters/L"},
  W = {0.1, Name "Parameters/W"},
  H = {0.1, Name "Parameters/H"},
  h = {0.05, Name "Parameters/h"}
];

Box(1) = {0, 0, 0, L, W, H};

eps = 1e-6 * L;
clamp[] = Surface In BoundingBox{-eps, -eps, -eps, eps, W + eps, H + eps};
tip[] = Surface In BoundingBox{L - eps, -eps, -eps, L + eps, W + eps, H + eps};

Physical Volume("beam", 1) = {1};
Physical Surface("clamp", 1) = {clamp[]};
Physical Surface("tip", 2) = {tip[]};

Mesh.CharacteristicLengthMax = h;
Mesh.CharacteristicLengthMin = 0;
