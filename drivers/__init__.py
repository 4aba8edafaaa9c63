"""Device drivers: one module per device family, each a wire codec plus the driver using it."""
