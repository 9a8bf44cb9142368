// Shock-protection scene for demos/shock_protection.py (2D): a cellular strip (a W x H slab with
// a row of n round holes of radius R, the thin curved ligaments between them buckle and the
// holes close when the strip is compressed) on a fixed base, and a load (a wl x hl block) a small
// gap above the middle of the strip. Physical groups: surfaces "strip" (cell tag 1), "load" (2);
// curve "base" (the strip's bottom, facet tag 1). Override the constants with -setnumber
// (diffsolids.mesh.from_geo's `numbers`).
SetFactory("OpenCASCADE");

DefineConstant[
  W = {0.48, Name "Parameters/W"},          // strip width and height
  H = {0.08, Name "Parameters/H"},
  n = {6, Name "Parameters/n"},             // holes, centred at ((k + 1/2) W / n, H / 2)
  R = {0.03, Name "Parameters/R"},          // hole radii (horizontal, vertical)
  Ry = {0.03, Name "Parameters/Ry"},
  wl = {0.3, Name "Parameters/wl"},         // load width and height
  hl = {0.05, Name "Parameters/hl"},
  gap = {0.002, Name "Parameters/gap"},     // initial gap between the load and the strip
  h = {0.01, Name "Parameters/h"},          // mesh size of the strip
  hload = {0.02, Name "Parameters/hload"}   // mesh size of the load
];

Rectangle(1) = {0, 0, 0, W, H};
For k In {0 : n - 1}
  Disk(10 + k) = {(k + 0.5) * W / n, H / 2, 0, R, Ry};
EndFor
strip[] = BooleanDifference{ Surface{1}; Delete; }{ Surface{10 : 10 + n - 1}; Delete; };
Rectangle(2) = {(W - wl) / 2, H + gap, 0, wl, hl};

eps = 1e-6;
base[] = Curve In BoundingBox{-eps, -eps, -eps, W + eps, eps, eps};

Physical Surface("strip", 1) = {strip[]};
Physical Surface("load", 2) = {2};
Physical Curve("base", 1) = {base[]};

MeshSize{PointsOf{Surface{strip[]};}} = h;
MeshSize{PointsOf{Surface{2};}} = hload;
Mesh.CharacteristicLengthMax = hload;
Mesh.CharacteristicLengthMin = 0;
