// Test mesh (tests/test_mesh.py): two boxes [0, 1] x [0, 1] x [0, 1] and [0, 1] x [0, 1] x [1, 1.5]
// glued conformingly. Bodies "base" (cell tag 1) and "cap" (2); surfaces "floor" (z = 0, facet
// tag 5) and "roof" (z = 1.5, 6).
SetFactory("OpenCASCADE");
DefineConstant[ h = {0.5, Name "Parameters/h"} ];

Box(1) = {0, 0, 0, 1, 1, 1};
Box(2) = {0, 0, 1, 1, 1, 0.5};
BooleanFragments{ Volume{1, 2}; Delete; }{}

eps = 1e-6;
floor[] = Surface In BoundingBox{-eps, -eps, -eps, 1 + eps, 1 + eps, eps};
roof[] = Surface In BoundingBox{-eps, -eps, 1.5 - eps, 1 + eps, 1 + eps, 1.5 + eps};
base[] = Volume In BoundingBox{-eps, -eps, -eps, 1 + eps, 1 + eps, 1 + eps};
cap[] = Volume In BoundingBox{-eps, -eps, 1 - eps, 1 + eps, 1 + eps, 1.5 + eps};

Physical Volume("base", 1) = {base[]};
Physical Volume("cap", 2) = {cap[]};
Physical Surface("floor", 5) = {floor[]};
Physical Surface("roof", 6) = {roof[]};

Mesh.CharacteristicLengthMax = h;
