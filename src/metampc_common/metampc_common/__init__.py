"""What every metampc node shares: main() and parameter declaration, typed parameters, QoS,
excitation signals."""
