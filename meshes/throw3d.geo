// Throw scene for demos/throw.py --full (3D): a static ground slab, a ball "A" (the thrown body)
// and a puck "B" (a short vertical cylinder) resting on the ground a small gap above it.
// B (3.1 kg at 1000 kg/m^3) is lighter than A (5.3 kg at 3000 kg/m^3), so a throw of a few
// m/s sends it sliding most of a metre.
// Physical groups: volumes "ground" (cell tag 1), "A" (2), "B" (3); surface "ground_top"
// (facet tag 1). Override the constants with -setnumber (diffsolids.mesh.from_geo's `numbers`).
SetFactory("OpenCASCADE");

DefineConstant[
  ground_x0 = {-0.6, Name "Parameters/ground_x0"},   // the ground's top is the triangle
  ground_x1 = {3.4, Name "Parameters/ground_x1"},    // (x0, -w), (x1, 0), (x0, w)
  ground_w = {1.5, Name "Parameters/ground_w"},
  ground_depth = {0.1, Name "Parameters/ground_depth"},
  ax = {0.1, Name "Parameters/ax"},                  // centre of ball A
  ay = {0.0, Name "Parameters/ay"},
  az = {0.085, Name "Parameters/az"},
  ar = {0.075, Name "Parameters/ar"},                // radius of ball A
  bx = {0.4, Name "Parameters/bx"},                  // axis of puck B
  by = {0.0, Name "Parameters/by"},
  br = {0.1, Name "Parameters/br"},                  // radius and height of puck B
  bh = {0.1, Name "Parameters/bh"},
  gap = {0.0005, Name "Parameters/gap"},             // initial gap between B and the ground
  h = {0.035, Name "Parameters/h"},                  // mesh size of the bodies
  hg = {10, Name "Parameters/hg"}                    // mesh size of the ground (see below)
];

// The ground is a static obstacle (all its nodes are held): a triangular prism meshed as
// coarsely as possible, so that its top is one triangle without inner edges. Ground vertices
// or edges under the sliding puck make the friction and barrier forces jitter whenever a puck
// vertex passes one, and with them the gradients.
Point(1) = {ground_x0, -ground_w, 0, hg};
Point(2) = {ground_x1, 0, 0, hg};
Point(3) = {ground_x0, ground_w, 0, hg};
Line(1) = {1, 2};
Line(2) = {2, 3};
Line(3) = {3, 1};
Curve Loop(1) = {1, 2, 3};
Plane Surface(1) = {1};
ground[] = Extrude {0, 0, -ground_depth} { Surface{1}; };
Sphere(20) = {ax, ay, az, ar};
Cylinder(30) = {bx, by, gap, 0, 0, bh, br};

Physical Volume("ground", 1) = {ground[1]};
Physical Volume("A", 2) = {20};
Physical Volume("B", 3) = {30};
Physical Surface("ground_top", 1) = {1};

MeshSize{PointsOf{Volume{ground[1]};}} = hg;
MeshSize{PointsOf{Volume{20, 30};}} = h;
Mesh.CharacteristicLengthMax = hg;
Mesh.CharacteristicLengthMin = 0;
