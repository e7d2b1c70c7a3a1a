// A breast-like dome on a flat chest wall, meshed by Gmsh (the shipped mesh case's test mesh).
// LPS millimetres: the wall is the plane y = 0, the breast hangs towards -y (anterior), prone.
SetFactory("OpenCASCADE");
Geometry.OCCBoundsUseStl = 1;  // tight bounding boxes for the selections below
Sphere(1) = {0, 0, 0, 1};
Dilate {{0, 0, 0}, {65, 55, 60}} { Volume{1}; }
Box(2) = {-100, 0, -100, 200, 100, 200};
BooleanDifference(3) = { Volume{1}; Delete; }{ Volume{2}; Delete; };
Sphere(4) = {0, 0, 0, 1};
Dilate {{0, 0, 0}, {30, 16, 26}} { Volume{4}; }
Translate {6, -27, 4} { Volume{4}; }
BooleanFragments{ Volume{3}; Delete; }{ Volume{4}; Delete; }
// After the fragments: the gland is the volume inside the small ellipsoid, the fat the rest.
gland() = Volume In BoundingBox{-30, -50, -30, 42, -4, 38};
all() = Volume{:};
fat() = all();
fat() -= gland();
wall() = Surface In BoundingBox{-66, -0.1, -61, 66, 0.1, 61};
surfaces() = Abs(Boundary{ Volume{fat()}; });
skin() = surfaces();
skin() -= wall();
skin() -= Abs(Boundary{ Volume{gland()}; });
Physical Volume("fat", 1) = {fat()};
Physical Volume("fibroglandular", 2) = {gland()};
Physical Surface("chest_wall", 11) = {wall()};
Physical Surface("skin", 12) = {skin()};
Mesh.MeshSizeMax = 5.5;
Mesh.MeshSizeMin = 2;
Mesh.Algorithm3D = 1;
Mesh.Optimize = 1;
Mesh.RandomSeed = 1;
Mesh.MshFileVersion = 2.2;
