"""From raw to calibrated kernel phases: calibrator subtraction, field rotation (angular
differential), the error model, covariance and whitening, nuisance terms.
"""
