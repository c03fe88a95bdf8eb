"""The text under each command's ``--help``: examples, and what a command does
beyond its options (kept apart from the options of `kpifs._cli._parser`)."""

EPILOG_KERNEL = """examples:
  kpifs kernel --pupil subaru --step 0.38m -o subaru_model.fits
  kpifs kernel --pupil vlt --step 0.4m --offset 0.1m,0.05m --grey -o vlt_grey.fits
  kpifs kernel --pupil mypupil.fits --pupil-scale 0.02m -o model.fits
"""
EPILOG_MODELCHECK = """Fits the turn of the pupil model and the pixel-scale factor to the Fourier
amplitudes of a star without a known companion, and compares transmission
cuts (and steps) by the calibrated reduced chi2 between two stars or between
the two halves of one sequence; prints every model tried and the one it
recommends, with the reason: another model than the default only when its
chi2 is lower by more than twice the noise of the difference.

examples:
  kpifs model-check calibrator.fits --wavelengths 2.145um --pixscale 25mas --pupil pharo
  kpifs model-check calibrator1.fits --calibrator calibrator2.fits --pupil subaru \\
      -o check.ecsv
  kpifs model-check calibrator.fits --rotations -3,-2,-1,0,1,2,3 --scales 0.99,1,1.01
"""
EPILOG_EXTRACT = """examples:
  kpifs extract cube.fits --wavelengths 1.52um,1.60um,1.68um --pixscale 10.42mas \\
      --pupil subaru -o kp.fits
  kpifs extract sim/target.fits --pupil model.fits -o kp.fits --overwrite
  kpifs extract target/CRSA*_cube.fits --calibrator calibrator/CRSA*_cube.fits \\
      -o calibrated_kp.fits
  kpifs extract target/science_cube.fits --instrument sphere \\
      --wavelengths target/wavelength.fits --calibrator calibrator/science_cube.fits \\
      -o calibrated_kp.fits
  kpifs extract calibrator/CRSA*_cube.fits -o calibrator_kp.fits
  kpifs extract cube.fits --pa 12.5,13.0,13.6 -o kp.fits
"""
EPILOG_DETECT = """examples:
  kpifs detect calibrated_kp.fits -o detection.fits --plots figures
  kpifs detect target_kp.fits --calibrator calibrator_kp.fits --test B-paper --pfa 1e-3 \\
      --max-sep 200mas --grid-step 5mas -o detection.fits
  kpifs detect calibrated_kp.fits --test NP --spectrum 1.3,1.0,0.7 -o detection.fits
detect reads kernel phases (KPFITS): make them from cubes with 'kpifs extract' first.
calibrated_kp.fits: a target's kernel phases with a calibrator's subtracted ('kpifs
extract TARGET --calibrator CALIBRATOR'); calibrator_kp.fits: a calibrator star's own.
the default test (--test auto) is S on data with more channels than its spectral
model's rank (3), else B; the printout says which test ran.
"""
EPILOG_BATCH = """examples:
  kpifs batch archive.csv -o reprocessed
  kpifs batch --glob 'night1/*_cube.fits' --calibrator 'night1/cal/*_cube.fits' -o out
  kpifs batch archive.csv --scheduler tcp://10.0.0.5:8786 -o reprocessed
manifest (CSV):
  name,target,calibrator
  hd1234,hd1234/CRSA*_cube.fits,ref1/CRSA*_cube.fits|ref2/CRSA*_cube.fits
every entry is reduced as 'kpifs extract TARGET --calibrator CAL' then 'kpifs detect'
would with the same options; exit status 1 if any entry failed (see summary.ecsv);
a rerun skips entries already done.
"""
EPILOG_INJECT = """examples:
  kpifs inject cube.fits --position 150,-80mas --contrast 5e-3 -o injected.fits
  kpifs inject target/CRSA*_cube.fits --position 120,40mas --sky --contrast 2e-3,1.5e-3 \\
      -o injected.fits
  kpifs inject target.fits --calibrator calibrator.fits --curve --separations 60,120mas \\
      -o curve.fits --plots figures
  kpifs inject target.fits --calibrator calibrator.fits --curve \\
      --separations 100,200mas --contrasts 1e-3,2e-3,5e-3,1e-2 --angles 6 -o curve.fits
an injected companion is each frame's own image, shifted and scaled (per channel);
--curve reruns the whole reduction for every injection and writes where the steps put
the contrast found half the time at --pfa, beside the analytic limit: between the
highest step found significantly less often and the lowest found significantly more
(with 4 angles: 0 and 4 of 4 found), a value interpolated only between adjacent such
steps, a bound where the steps reach no such step on one side.
"""
EPILOG_INFO = """examples:
  kpifs info target/CRSA00000000_cube.fits
  kpifs info kp.fits
  kpifs info detection.fits curve.fits
  kpifs info --instruments            # the instruments kpifs reads
"""
EPILOG_SIMULATE = """examples:
  kpifs simulate --preset paper --frames 100 -o sim
  kpifs simulate --preset charis --layout charis --frames 5 -o charis_sim
  kpifs simulate --preset sphere --layout sphere -o sphere_sim
  kpifs simulate --preset niriss --layout jwst -o niriss_sim   # NIRISS _calints.fits
  kpifs simulate --preset gpi --layout gpi -o gpi_sim          # GPI _spdc.fits
  kpifs simulate --preset nirc2 --layout nirc2 -o nirc2_sim    # Keck/NIRC2 images
  kpifs simulate --preset charis --frames 40 --drift 40nm --drift-time 8 \\
      --static-diff 15nm -o unkind     # drifting aberrations, target != calibrator
  kpifs simulate --preset charis --layout charis --rotation 40deg -o turning
  kpifs simulate --preset sphere --layout sphere --hour-angle=-1,1 --declination=-40 \\
      -o transit                       # parallactic angles at Paranal
presets: paper (the seed paper's Subaru scene: 3 channels at 1.52-1.68 um, 40x40 pixels
of 10.42 mas, 1000 frames), charis (22 channels at 1.16-2.37 um, 201x201 pixels of
16.2 mas, 20 frames), sphere (VLT, 39 channels at 0.96-1.33 um, 64x64 pixels of
7.46 mas, 20 frames).
"""
