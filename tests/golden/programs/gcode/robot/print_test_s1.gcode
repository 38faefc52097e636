; fabflow G-code program print test S1 (robot flavor)
; project: writer test
; station: S1
; generator: fabflow test
; robot: kuka_kr60_3
; tool: extruder
; print paths (bead width x height, mm): P1 40.0 x 20.0, P2 40.0 x 20.0
; units: millimetres (G21), absolute positions (G90), feed rate F in mm/min
; frame: X Y Z are the tool centre point in the robot base frame at this station
; T_base_world (the design world in the robot base frame; rotation rows, then mm):
; row 1: 0.9950042 0.0998334 0.0000000 -2089.842
; row 2: -0.0998334 0.9950042 0.0000000 -795.337
; row 3: 0.0000000 0.0000000 1.0000000 -600.000
; E: deposited volume of the beads (mm^3), absolute, 0 at the start
; G0: travel (a joint move in the robot program); G1: straight line
; tool axis at the first print move, base frame: 0.0000 0.0000 -1.0000 (orientation is not carried)
G21
G90
; OPERATOR: set the lift to 350 mm above its lowest position, then resume
M0
; joint target (home): 0.000 -90.000 90.000 0.000 0.000 0.000 deg
G0 X1590.000 Y0.000 Z1810.000
; element P1
G0 X1353.072 Y-537.768 Z-200.000
G1 X1353.072 Y-537.768 Z-300.000 F15000.0
; extruder on
G1 X1457.565 Y-498.002 Z-300.000 E89442.719 F6000.0
G1 X1552.073 Y-557.735 Z-300.000 E178885.438
; extruder off
G1 X1552.073 Y-557.735 Z-200.000 F15000.0
; element P2
G0 X1353.072 Y-537.768 Z-180.000
G1 X1353.072 Y-537.768 Z-280.000
; extruder on
G1 X1457.565 Y-498.002 Z-280.000 E268328.157 F3000.0
; extruder off
G1 X1552.073 Y-557.735 Z-280.000 F15000.0
; extruder on
G1 X1562.057 Y-458.235 Z-280.000 E348328.157 F3000.0
; extruder off
G1 X1562.057 Y-458.235 Z-180.000 F15000.0
; joint target (home): 0.000 -90.000 90.000 0.000 0.000 0.000 deg
G0 X1590.000 Y0.000 Z1810.000
; end of program
