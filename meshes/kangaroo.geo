// A small 2D "kangaroo" for demos/kangaroo_material.py: a body (ellipse) with a head, neck,
// arm, two legs with feet and a long tail, standing GAP above a ground slab whose top face is
// y = 0. Lengths in metres (about 1 m long, 0.85 m tall).
// Physical groups: "ground" (cell tag 1), "kangaroo" (cell tag 2); "ground_bottom" (facet tag
// 1, y = -GT). Override the constants with -setnumber (diffsolids.mesh.from_geo's `numbers`).
SetFactory("OpenCASCADE");

DefineConstant[
  GAP = {0.01, Name "Parameters/GAP"},  // initial gap between the feet and the ground
  GL = {2.4, Name "Parameters/GL"},     // ground length (from x = -0.9)
  GT = {0.05, Name "Parameters/GT"},    // ground thickness
  h = {0.03, Name "Parameters/h"},      // mesh size of the kangaroo
  hg = {0.08, Name "Parameters/hg"}     // mesh size of the ground
];

Disk(1) = {0, 0.5, 0, 0.24, 0.15};                     // body
Disk(2) = {0.25, 0.74, 0, 0.07, 0.07};                 // head
Rectangle(3) = {0.08, 0.52, 0, 0.27, 0.07, 0.02};      // neck (reaches into the head)
Rotate {{0, 0, 1}, {0.08, 0.52, 0}, Pi / 4} { Surface{3}; }
Rectangle(4) = {-0.14, 0.03, 0, 0.06, 0.4, 0.02};      // back leg
Rectangle(5) = {-0.16, 0, 0, 0.2, 0.05, 0.02};         // back foot
Rectangle(6) = {0.05, 0.03, 0, 0.06, 0.4, 0.02};       // front leg
Rectangle(7) = {0.03, 0, 0, 0.2, 0.05, 0.02};          // front foot
Rectangle(8) = {-0.62, 0.42, 0, 0.45, 0.06, 0.02};     // tail
Rotate {{0, 0, 1}, {-0.17, 0.45, 0}, Pi / 9} { Surface{8}; }
Rectangle(9) = {0.15, 0.36, 0, 0.14, 0.04, 0.015};     // arm
Rotate {{0, 0, 1}, {0.15, 0.38, 0}, -Pi / 5} { Surface{9}; }
body[] = BooleanUnion{ Surface{1}; Delete; }{ Surface{2 : 9}; Delete; };
Translate {0, GAP, 0} { Surface{body[]}; }
Rectangle(20) = {-0.9, -GT, 0, GL, GT};

Physical Surface("ground", 1) = {20};
Physical Surface("kangaroo", 2) = {body[]};
eps = 1e-6;
bottom[] = Curve In BoundingBox{-0.9 - eps, -GT - eps, -eps, -0.9 + GL + eps, -GT + eps, eps};
Physical Curve("ground_bottom", 1) = {bottom[]};

MeshSize{ PointsOf{ Surface{body[]}; } } = h;
MeshSize{ PointsOf{ Surface{20}; } } = hg;
Mesh.CharacteristicLengthMax = hg;
Mesh.CharacteristicLengthMin = 0;
