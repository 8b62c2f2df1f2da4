// Seed 001 pseudo-2D bed (Hamidouche et al. 2019, Fluids 4:51), Table 2: structured hexahedra with a
// centred bottom-wall patch where no gas enters. Coarse level by default; other levels:
//   gmsh -3 pseudo2d.geo -setnumber nx 35 -setnumber ny 6 -setnumber nz 110 -setnumber px 5 -setnumber py 4
//   gmsh -3 pseudo2d.geo -setnumber nx 70 -setnumber ny 12 -setnumber nz 220 -setnumber px 10 -setnumber py 8
// Same geometry as febed.meshing.build_msh("pseudo2d", level=...); tests/test_meshing.py checks they agree.
DefineConstant[ nx = 17, ny = 3, nz = 55, px = 3, py = 3 ];
Lx = 0.08; Ly = 0.015; Lz = 0.25;
sx = (nx - px) / 2; sy = (ny - py) / 2;

// strips [side, patch, side] in x and y, leaving out empty ones
cx[] = {}; xs[] = {0};
If (sx > 0) cx[] += {sx}; xs[] += {sx * Lx / nx}; EndIf
cx[] += {px}; xs[] += {(sx + px) * Lx / nx};
If (sx > 0) cx[] += {sx}; xs[] += {Lx}; EndIf
cy[] = {}; ys[] = {0};
If (sy > 0) cy[] += {sy}; ys[] += {sy * Ly / ny}; EndIf
cy[] += {py}; ys[] += {(sy + py) * Ly / ny};
If (sy > 0) cy[] += {sy}; ys[] += {Ly}; EndIf
NX = #cx[]; NY = #cy[];
ip = (sx > 0) ? 1 : 0; jp = (sy > 0) ? 1 : 0;

For i In {0 : NX}
  For j In {0 : NY}
    pt[i * (NY + 1) + j] = newp; Point(pt[i * (NY + 1) + j]) = {xs[i], ys[j], 0};
  EndFor
EndFor
For i In {0 : NX - 1}
  For j In {0 : NY}
    hl[i * (NY + 1) + j] = newl;
    Line(hl[i * (NY + 1) + j]) = {pt[i * (NY + 1) + j], pt[(i + 1) * (NY + 1) + j]};
    Transfinite Curve{hl[i * (NY + 1) + j]} = cx[i] + 1;
  EndFor
EndFor
For i In {0 : NX}
  For j In {0 : NY - 1}
    vl[i * NY + j] = newl;
    Line(vl[i * NY + j]) = {pt[i * (NY + 1) + j], pt[i * (NY + 1) + j + 1]};
    Transfinite Curve{vl[i * NY + j]} = cy[j] + 1;
  EndFor
EndFor

inlet[] = {}; outlet[] = {}; walls[] = {}; vols[] = {};
For i In {0 : NX - 1}
  For j In {0 : NY - 1}
    cl = newll;
    Curve Loop(cl) = {hl[i * (NY + 1) + j], vl[(i + 1) * NY + j], -hl[i * (NY + 1) + j + 1], -vl[i * NY + j]};
    s = news; Plane Surface(s) = {cl};
    Transfinite Surface{s}; Recombine Surface{s};
    If (i == ip && j == jp) patch = s; Else inlet[] += {s}; EndIf
    // out[0] top, out[1] volume, out[2..5] sides at y = ys[j], x = xs[i+1], y = ys[j+1], x = xs[i]
    out[] = Extrude {0, 0, Lz} { Surface{s}; Layers{nz}; Recombine; };
    outlet[] += {out[0]}; vols[] += {out[1]};
    If (j == 0) walls[] += {out[2]}; EndIf
    If (i == NX - 1) walls[] += {out[3]}; EndIf
    If (j == NY - 1) walls[] += {out[4]}; EndIf
    If (i == 0) walls[] += {out[5]}; EndIf
  EndFor
EndFor
Physical Surface("bottom_wall") = {patch};
Physical Surface("inlet") = {inlet[]};
Physical Surface("outlet") = {outlet[]};
Physical Surface("walls") = {walls[]};
Physical Volume("fluid") = {vols[]};
