// Throw scene for demos/throw.py (2D): a static ground slab, a disk "A" (the thrown body) and a
// rounded block "B" resting on the ground a small gap above it. Physical groups: surfaces
// "ground" (cell tag 1), "A" (2), "B" (3); curve "ground_top" (facet tag 1). Override the
// constants with -setnumber (diffsolids.mesh.from_geo's `numbers`).
SetFactory("OpenCASCADE");

DefineConstant[
  ground_x0 = {-0.4, Name "Parameters/ground_x0"},
  ground_x1 = {2.4, Name "Parameters/ground_x1"},
  ground_depth = {0.1, Name "Parameters/ground_depth"},
  ax = {0.1, Name "Parameters/ax"},      // centre of disk A
  ay = {0.085, Name "Parameters/ay"},
  ar = {0.07, Name "Parameters/ar"},      // radius of disk A
  bx = {0.4, Name "Parameters/bx"},       // lower left corner of block B
  bw = {0.36, Name "Parameters/bw"},       // width and height of block B
  bh = {0.16, Name "Parameters/bh"},
  br = {0.03, Name "Parameters/br"},      // corner radius of block B
  gap = {0.0005, Name "Parameters/gap"},  // initial gap between B and the ground
  h = {0.04, Name "Parameters/h"},        // mesh size of the bodies
  hg = {10, Name "Parameters/hg"}         // mesh size of the ground (see below)
];

Rectangle(1) = {ground_x0, -ground_depth, 0, ground_x1 - ground_x0, ground_depth};
Disk(2) = {ax, ay, 0, ar, ar};
Rectangle(3) = {bx, gap, 0, bw, bh, br};

eps = 1e-6;
top[] = Curve In BoundingBox{ground_x0 - eps, -eps, -eps, ground_x1 + eps, eps, eps};

Physical Surface("ground", 1) = {1};
Physical Surface("A", 2) = {2};
Physical Surface("B", 3) = {3};
Physical Curve("ground_top", 1) = {top[]};

// The ground is a static obstacle (all its nodes are held): it is meshed as coarsely as possible,
// so that its top is one straight edge. Ground vertices under the sliding block make the friction
// and barrier forces jitter whenever a block vertex passes one, and with them the gradients.
MeshSize{PointsOf{Surface{1};}} = hg;
MeshSize{PointsOf{Surface{2, 3};}} = h;
Mesh.CharacteristicLengthMax = hg;
Mesh.CharacteristicLengthMin = 0;
