"""What the controller is fed besides its configuration: trajectory sources and drift
measured from AFM images."""
