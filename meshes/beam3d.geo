// 3D beam for demos/beam3d_stress.py: a box [0, L] x [0, W] x [0, H] standing on a support
// patch in the middle of its underside (|x - L/2| <= S/2, z = 0), loaded on its two end faces.
// Physical groups: volume "beam" (cell tag 1); surfaces "support" (the patch, facet tag 1),
// "load_left" (x = 0, 2) and "load_right" (x = L, 3). Override the constants with -setnumber
// (diffsolids.mesh.from_geo's `numbers`), e.g. {"h": 0.05}.
SetFactory("OpenCASCADE");

DefineConstant[
  L = {2.0, Name "Parameters/L"},    // length
  W = {0.25, Name "Parameters/W"},   // width (y)
  H = {0.25, Name "Parameters/H"},   // height (z)
  S = {0.3, Name "Parameters/S"},    // length of the support patch
  h = {0.06, Name "Parameters/h"}    // mesh size
];

Box(1) = {0, 0, 0, L, W, H};
Rectangle(100) = {L / 2 - S / 2, 0, 0, S, W};  // the support patch on the underside
BooleanFragments{ Volume{1}; Delete; }{ Surface{100}; Delete; }

eps = 1e-6 * L;
support[] = Surface In BoundingBox{L / 2 - S / 2 - eps, -eps, -eps, L / 2 + S / 2 + eps, W + eps, eps};
left[] = Surface In BoundingBox{-eps, -eps, -eps, eps, W + eps, H + eps};
right[] = Surface In BoundingBox{L - eps, -eps, -eps, L + eps, W + eps, H + eps};

Physical Volume("beam", 1) = {Volume{:}};
Physical Surface("support", 1) = {support[]};
Physical Surface("load_left", 2) = {left[]};
Physical Surface("load_right", 3) = {right[]};

Mesh.CharacteristicLengthMax = h;
Mesh.CharacteristicLengthMin = 0;
